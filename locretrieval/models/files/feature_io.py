"""Global descriptors in other tools' formats: kapture ``global_features`` out, hloc HDF5 in.

kapture (>= 1.1): ``<kapture>/reconstruction/global_features/<feature_name>/`` holds
``global_features.txt`` (``name, dtype, dsize, metric_type``) and one raw ``.gfeat`` file per
image, at the image's records_data name plus ``.gfeat`` (what `PrecomputedDescriptor` reads).
hloc: an HDF5 file with one group per image name (``/`` in names nests groups) holding a
``global_descriptor`` dataset, read within `locretrieval.bounded_files`' budgets (no link followed).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import h5py
import kapture
import kapture.io.csv
import kapture.io.features
import numpy as np

from locretrieval.bounded_files import hdf5_member, open_hdf5, read_dataset
from locretrieval.errors import FIX_DATA_FILE


def export_global_features(
    names: Sequence[str],
    descriptors: np.ndarray,
    folder: str | os.PathLike,
    feature_name: str,
    metric_type: str = "L2",
) -> Path:
    """Write ``descriptors[i]`` of image ``names[i]`` as kapture global features of the kapture
    folder ``folder``, with kapture's writers; returns the feature folder."""
    descriptors = np.asarray(descriptors)
    if descriptors.ndim != 2 or len(descriptors) != len(names):
        raise ValueError(f"{len(names)} image names but descriptors of shape {descriptors.shape}")
    if len(set(names)) != len(names):
        raise ValueError("duplicate image names: each image has exactly one global-feature file")
    kapture_dir = str(folder)
    config = kapture.GlobalFeatures(feature_name, descriptors.dtype, descriptors.shape[1], metric_type)
    kapture.io.csv.global_features_to_file(
        kapture.io.csv.get_feature_csv_fullpath(kapture.GlobalFeatures, feature_name, kapture_dir), config
    )
    for name, descriptor in zip(names, descriptors):
        path = kapture.io.features.get_global_features_fullpath(feature_name, kapture_dir, name)
        kapture.io.features.image_global_features_to_file(path, np.ascontiguousarray(descriptor))
    return Path(kapture.io.csv.get_feature_csv_fullpath(kapture.GlobalFeatures, feature_name, kapture_dir)).parent


def read_hloc_global_descriptors(path: str | os.PathLike, names: Sequence[str]) -> np.ndarray:
    """``float32 [len(names), D]`` global descriptors of ``names`` from an hloc features file
    (values as stored, e.g. widened from float16; not re-normalised)."""
    rows = []
    with open_hdf5(path, "hloc features file", FIX_DATA_FILE) as file:
        for name in names:
            dataset = hdf5_member(file, f"{name}/global_descriptor", path)
            if not isinstance(dataset, h5py.Dataset):
                raise KeyError(f"{path}: no global_descriptor for image {name!r}")
            rows.append(np.asarray(read_dataset(dataset, path), dtype=np.float32).reshape(-1))
    dims = {len(row) for row in rows}
    if len(dims) > 1:
        raise ValueError(f"{path}: global descriptors of different sizes {sorted(dims)}")
    return np.stack(rows) if rows else np.zeros((0, 0), dtype=np.float32)
