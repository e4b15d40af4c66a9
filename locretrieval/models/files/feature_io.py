"""Global descriptors in other tools' formats: kapture ``global_features`` out, hloc HDF5 out and in.

kapture (>= 1.1): ``<kapture>/reconstruction/global_features/<feature_name>/`` holds
``global_features.txt`` (``name, dtype, dsize, metric_type``) and one raw ``.gfeat`` file per
image, at the image's records_data name plus ``.gfeat`` (what `PrecomputedDescriptor` reads).
hloc: an HDF5 file with one group per image name (``/`` in names nests groups) holding a
``global_descriptor`` dataset, as hloc's ``extract_features`` writes it and ``pairs_from_retrieval``
reads it (``file[name]["global_descriptor"]``), read within `locretrieval.bounded_files`' budgets
(no link followed). Names written are checked first (`locretrieval.scene.names.check_exported_names`):
none leads outside the folder or file written.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Sequence
from pathlib import Path

import h5py
import kapture
import kapture.io.csv
import kapture.io.features
import numpy as np

from locretrieval.bounded_files import hdf5_member, open_hdf5, read_dataset
from locretrieval.cache import atomic_path, safe_name
from locretrieval.errors import FIX_DATA_FILE
from locretrieval.scene.names import check_exported_names, inside


def export_global_features(
    names: Sequence[str],
    descriptors: np.ndarray,
    folder: str | os.PathLike,
    feature_name: str,
    metric_type: str = "L2",
) -> Path:
    """Write ``descriptors[i]`` of image ``names[i]`` as kapture global features of the kapture
    folder ``folder``, with kapture's writers; returns the feature folder."""
    descriptors = _descriptor_rows(names, descriptors)
    if safe_name(feature_name) != feature_name:
        raise ValueError(f"feature name {feature_name[:200]!r} is not one folder name (e.g. {safe_name(feature_name)})")
    check_exported_names(names, f"kapture global features {feature_name}")
    kapture_dir = str(folder)
    config = kapture.GlobalFeatures(feature_name, descriptors.dtype, descriptors.shape[1], metric_type)
    header = Path(kapture.io.csv.get_feature_csv_fullpath(kapture.GlobalFeatures, feature_name, kapture_dir))
    kapture.io.csv.global_features_to_file(str(header), config)
    for name, descriptor in zip(names, descriptors):
        path = kapture.io.features.get_global_features_fullpath(feature_name, kapture_dir, name)
        kapture.io.features.image_global_features_to_file(
            str(inside(header.parent, path)), np.ascontiguousarray(descriptor)
        )
    return header.parent


def write_hloc_global_descriptors(path: str | os.PathLike, names: Sequence[str], descriptors: np.ndarray) -> Path:
    """Write ``descriptors[i]`` of image ``names[i]`` as hloc's global-features file ``path``
    (written whole or not at all); returns ``path``."""
    descriptors = _descriptor_rows(names, descriptors)
    check_exported_names(names, f"hloc global features {path}")
    with atomic_path(path) as temporary:
        with h5py.File(temporary, "w") as file:
            for name, descriptor in zip(names, descriptors):
                file.require_group(name).create_dataset("global_descriptor", data=descriptor)
    return Path(path)


def _descriptor_rows(names: Sequence[str], descriptors: np.ndarray) -> np.ndarray:
    """``descriptors`` as an array of one row per name; ``ValueError`` otherwise."""
    descriptors = np.asarray(descriptors)
    if descriptors.ndim != 2 or len(descriptors) != len(names):
        raise ValueError(f"{len(names)} image names but descriptors of shape {descriptors.shape}")
    return descriptors


def read_hloc_global_descriptors(
    paths: str | os.PathLike | Sequence[str | os.PathLike], names: Sequence[str]
) -> np.ndarray:
    """``float32 [len(names), D]`` global descriptors of ``names`` from hloc features files (one
    path or a list: each image from the first file holding it), values as stored (e.g. widened
    from float16; not re-normalised). A missing image, a dataset that is not numeric and
    descriptors of different sizes are errors naming the file(s)."""
    files = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    where = ", ".join(str(file) for file in files)
    rows = []
    with contextlib.ExitStack() as stack:
        opened = [(stack.enter_context(open_hdf5(file, "hloc features file", FIX_DATA_FILE)), file) for file in files]
        for name in names:
            found = next(
                (
                    (dataset, file)
                    for opened_file, file in opened
                    if isinstance(dataset := hdf5_member(opened_file, f"{name}/global_descriptor", file), h5py.Dataset)
                ),
                None,
            )
            if found is None:
                raise KeyError(f"{where}: no global_descriptor for image {name!r}")
            dataset, file = found
            if dataset.dtype.kind not in "fiu":
                raise ValueError(f"{file}: global_descriptor of image {name!r} is {dataset.dtype}")
            rows.append(np.asarray(read_dataset(dataset, file), dtype=np.float32).reshape(-1))
    dims = {len(row) for row in rows}
    if len(dims) > 1:
        raise ValueError(f"{where}: global descriptors of different sizes {sorted(dims)}")
    return np.stack(rows) if rows else np.zeros((0, 0), dtype=np.float32)
