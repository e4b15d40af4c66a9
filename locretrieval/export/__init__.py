"""What the benchmark computes, in the formats the field's tools read (``export.py``, docs/export.md).

- `pairs`: each ranking's top k as pairs files, hloc's (``query db`` per line, best first) and
  kapture's (``query, db, score``), named by the images' kapture names;
- `scene`: a scene's rankings as pairs files and a descriptor model's global descriptors as
  kapture ``global_features`` and hloc's global-features HDF5 (the writers are
  `locretrieval.models.files.feature_io`'s);
- `network`: a torch descriptor's network as other tools run it (`DescriptorNetwork`), built from a
  locretrieval checkpoint alone for the ``locretrieval`` torch.hub entry point (``hubconf.py``);
- `onnx`: that network as ONNX with a dynamic batch dimension, checked against torch under onnxruntime;
- `run`: the run behind ``export.py``.

Every image name written is checked first (`locretrieval.scene.names.check_exported_names`) and
every file name made of a ranking or model name goes through `locretrieval.cache.safe_name`:
nothing is written outside the chosen folder.
"""
