"""Descriptors out as kapture global features, in from hloc HDF5 files."""

import h5py
import helpers
import kapture
import kapture.io.csv
import kapture.io.features
import numpy as np
import pytest

from locretrieval.models.files.feature_io import export_global_features, read_hloc_global_descriptors
from locretrieval.scene import Camera, ImageSet

NAMES = ["db/seq1/000.jpg", "db/seq1/001.jpg", "query/night/q.jpg"]


def unit_rows(rows: int, dim: int, seed: int = 0) -> np.ndarray:
    values = np.random.default_rng(seed).normal(size=(rows, dim)).astype(np.float32)
    return values / np.linalg.norm(values, axis=1, keepdims=True)


def test_exported_features_read_back_with_kapture_and_the_precomputed_model(tmp_path):
    descriptors = unit_rows(len(NAMES), 24)
    folder = export_global_features(NAMES, descriptors, tmp_path / "kapture", "Resnet101-AP-GeM-LM18")
    assert folder == tmp_path / "kapture" / "reconstruction" / "global_features" / "Resnet101-AP-GeM-LM18"

    features = kapture.io.csv.global_features_from_dir("Resnet101-AP-GeM-LM18", str(tmp_path / "kapture"), None)
    assert set(features) == set(NAMES) and features.dsize == 24 and features.metric_type == "L2"
    for name, row in zip(NAMES, descriptors):
        path = kapture.io.features.get_global_features_fullpath(
            "Resnet101-AP-GeM-LM18", str(tmp_path / "kapture"), name
        )
        np.testing.assert_array_equal(
            kapture.io.features.image_global_features_from_file(path, features.dtype, 24).reshape(-1), row
        )

    camera = Camera("PINHOLE", 8, 8, (4.0, 4.0, 4.0, 4.0))
    images = ImageSet(NAMES, tmp_path, [camera] * 3, [[1.0, 0, 0, 0]] * 3, [[0.0, 0, 0]] * 3)
    np.testing.assert_allclose(helpers.precomputed(path=folder).describe(images), descriptors, atol=1e-7)


def test_export_refuses_mismatched_names(tmp_path):
    with pytest.raises(ValueError, match="2 image names"):
        export_global_features(NAMES[:2], unit_rows(3, 4), tmp_path, "x")


@pytest.mark.smoke
def test_hloc_global_descriptors_are_read_by_image_name(tmp_path):
    descriptors = unit_rows(len(NAMES), 16, seed=1).astype(np.float16)
    path = tmp_path / "global-feats-netvlad.h5"
    with h5py.File(path, "w") as file:
        for name, row in zip(NAMES, descriptors):
            file.create_group(name).create_dataset("global_descriptor", data=row)  # nested groups, as hloc
    order = [NAMES[2], NAMES[0]]
    read = read_hloc_global_descriptors(path, order)
    assert read.dtype == np.float32
    np.testing.assert_array_equal(read, descriptors[[2, 0]].astype(np.float32))
    with pytest.raises(KeyError, match="global-feats-netvlad.h5: no global_descriptor for image 'db/missing.jpg'"):
        read_hloc_global_descriptors(path, ["db/missing.jpg"])
