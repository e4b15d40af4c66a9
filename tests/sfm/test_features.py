"""Local features (pycolmap SIFT, kapture files), matching, verification and their caches."""

from pathlib import Path

import helpers
import kapture
import kapture.io.csv as kapture_csv
import kapture.io.features as kapture_features
import numpy as np
import pytest
from local_features import SFM, GridFeatures, features
from omegaconf import OmegaConf

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.config import ConfigError, validated
from locretrieval.scene import Camera, ImageSet
from locretrieval.sfm import features as features_module
from locretrieval.sfm.features import extract_features
from locretrieval.sfm.matching import PairMatcher
from locretrieval.sfm.settings import SfmSettings
from locretrieval.sfm.verification import PoseVerification


def test_sift_features_are_cached_and_in_full_resolution_pixels(scene, tmp_path):
    database = scene.database.subset(np.arange(4))
    full = extract_features(database, SFM.features, tmp_path, workers=1)
    shards = sorted(full.folder.iterdir())
    again = extract_features(database, SFM.features, tmp_path, workers=1)
    assert sorted(again.folder.iterdir()) == shards  # nothing recomputed
    half = extract_features(database, features({"max_side": 128}), tmp_path, workers=1)
    assert half.folder != full.folder
    for name in database.names:
        keypoints, descriptors = full.load([name])[name]
        assert len(keypoints) > 10 and descriptors.shape == (len(keypoints), 128) and descriptors.dtype == np.uint8
        small = half.keypoints([name])[name]
        # scaled back to the 256 x 192 image: spans it, stays inside it
        assert (
            small[:, 0].max() > 200 and (small >= 0).all() and (small[:, 0] <= 256).all() and (small[:, 1] <= 192).all()
        )
        # half-resolution keypoints land on full-resolution ones (same structures, coarser)
        distance = np.linalg.norm(small[:, None] - keypoints[None], axis=-1).min(axis=1)
        assert np.median(distance) < 1.5


def test_feature_extraction_in_worker_processes_matches_in_process(scene, tmp_path, monkeypatch):
    monkeypatch.setattr(features_module, "IMAGES_PER_SHARD", 4)  # three tasks for two workers
    database = scene.database.subset(np.arange(12))
    parallel = extract_features(database, SFM.features, tmp_path / "parallel", workers=2)
    serial = extract_features(database, SFM.features, tmp_path / "serial", workers=1)
    assert len(list(parallel.folder.glob("*.h5"))) == 3
    for name in database.names:
        for a, b in zip(parallel.load([name])[name], serial.load([name])[name]):
            np.testing.assert_array_equal(a, b)


def write_kapture_features(
    root: Path, names: list[str], keypoints: list[np.ndarray], descriptors: list[np.ndarray]
) -> None:
    """Keypoints and descriptors files as the published kapture features (e.g. R2D2) are laid out."""
    kapture_dir = str(root)
    kapture_csv.keypoints_to_file(
        kapture_csv.get_feature_csv_fullpath(kapture.Keypoints, "r2d2", kapture_dir),
        kapture.Keypoints("r2d2", np.float32, 3),
    )
    kapture_csv.descriptors_to_file(
        kapture_csv.get_feature_csv_fullpath(kapture.Descriptors, "r2d2", kapture_dir),
        kapture.Descriptors("r2d2", np.float32, 128, "r2d2", "L2"),
    )
    for name, points, values in zip(names, keypoints, descriptors):
        kapture_features.image_keypoints_to_file(
            kapture_features.get_keypoints_fullpath("r2d2", kapture_dir, name), points
        )
        kapture_features.image_descriptors_to_file(
            kapture_features.get_descriptors_fullpath("r2d2", kapture_dir, name), values
        )


def kapture_folder_with_features(root: Path, names: list[str], counts: tuple[int, ...], seed: int):
    """Two images of a kapture folder at ``root`` with ``counts`` random R2D2-style keypoints
    (x, y, scale) and descriptors: the image set, keypoints and descriptors."""
    rng = np.random.default_rng(seed)
    camera = Camera("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
    images = ImageSet(
        names, root / "sensors" / "records_data", [camera] * 2, np.tile([1.0, 0, 0, 0], (2, 1)), np.zeros((2, 3))
    )
    keypoints = [rng.uniform(0, 40, (n, 3)).astype(np.float32) for n in counts]
    descriptors = [rng.normal(size=(n, 128)).astype(np.float32) for n in counts]
    write_kapture_features(root, names, keypoints, descriptors)
    return images, keypoints, descriptors


def test_kapture_features_are_read_with_the_pixel_offset(tmp_path):
    names = ["db/a.jpg", "db/sub/b.jpg"]
    root = tmp_path / "mapping"
    images, keypoints, descriptors = kapture_folder_with_features(root, names, (7, 3), 0)
    config = {"name": "r2d2", "pixel_offset": 0.5}
    store = extract_features(images, features(config, "kapture"), tmp_path / "cache", workers=1)
    for name, points, values in zip(names, keypoints, descriptors):
        read_points, read_values = store.load([name])[name]
        np.testing.assert_allclose(read_points, points[:, :2] + 0.5)
        np.testing.assert_array_equal(read_values, values)
    (root / "reconstruction" / "descriptors" / "r2d2" / "db" / "sub" / "b.jpg.desc").unlink()
    with pytest.raises(
        FileNotFoundError, match=r"descriptors 'r2d2' of image 'db/sub/b.jpg' not found: .*b\.jpg\.desc"
    ):
        extract_features(images, features({**config, "pixel_offset": 0.0}, "kapture"), tmp_path / "cache", workers=1)
    with pytest.raises(
        ConfigError,
        match=r"sfm.features.nmae: unknown key; expected one of "
        r"\['max_keypoints', 'name', 'pixel_offset', 'score_order'\]",
    ):
        features({"nmae": "r2d2"}, "kapture")


def test_a_keypoint_budget_keeps_the_best_rows_of_kapture_features_by_their_score_order(tmp_path):
    images, keypoints, descriptors = kapture_folder_with_features(
        tmp_path / "mapping", ["db/a.jpg", "db/b.jpg"], (9, 4), 5
    )
    for order, rows in [("ascending", slice(4, 9)), ("descending", slice(0, 5))]:  # R2D2 writes the best last
        config = {"max_keypoints": 5, "name": "r2d2", "pixel_offset": 0.0, "score_order": order}
        store = extract_features(images, features(config, "kapture"), tmp_path / "cache", workers=1)
        read_points, read_values = store.load(["db/a.jpg"])["db/a.jpg"]
        np.testing.assert_array_equal(read_points, keypoints[0][rows, :2])
        np.testing.assert_array_equal(read_values, descriptors[0][rows])
        assert len(store.keypoints(["db/b.jpg"])["db/b.jpg"]) == 4  # fewer than the budget: all
    with pytest.raises(
        ConfigError, match=r"sfm.features.max_keypoints: needs the score order of the kapture features 'r2d2'"
    ):
        features({"max_keypoints": 5, "score_order": None}, "kapture")


def test_a_keypoint_budget_keeps_pycolmaps_strongest_sift_detections(scene, tmp_path):
    database = scene.database.subset(np.arange(3))
    full = extract_features(database, SFM.features, tmp_path, workers=1)
    budget = extract_features(database, features({"max_keypoints": 12}), tmp_path, workers=1)
    assert budget.folder != full.folder
    for name in database.names:
        all_points, kept = full.keypoints([name])[name], budget.keypoints([name])[name]
        assert len(all_points) > 20 and len(kept) == 12
        assert len(np.unique(kept, axis=0)) >= 10  # extra orientations of a detection come last
        # the budget's keypoints are among the full set's (the same detector, its strongest detections)
        assert np.linalg.norm(kept[:, None] - all_points[None], axis=-1).min(axis=1).max() < 1e-3


def test_sift_budget_prefers_new_locations_to_extra_orientations():
    points = np.array([[1, 1], [1, 1], [2, 2], [3, 3], [3, 3], [4, 4]], dtype=np.float32)  # pycolmap's order

    def sift(budget):
        return features_module.SiftFeatures(budget, 1600, 0, 8192, 0.004)

    np.testing.assert_array_equal(sift(4).best_rows(points), [0, 2, 3, 5])
    np.testing.assert_array_equal(sift(5).best_rows(points), [0, 1, 2, 3, 5])
    np.testing.assert_array_equal(sift(None).best_rows(points), np.arange(6))


@pytest.mark.parametrize(("order", "expected"), [("ascending", [3, 4, 5]), ("descending", [0, 1, 2])])
def test_kapture_budget_keeps_the_best_scored_rows_of_the_files_order(order, expected):
    features = features_module.KaptureFeatures(3, "r2d2", 0.5, order)
    np.testing.assert_array_equal(features.best_rows(np.zeros((6, 2), np.float32)), expected)
    np.testing.assert_array_equal(features.best_rows(np.zeros((3, 2), np.float32)), [0, 1, 2])


def test_local_features_and_a_verification_from_outside_the_package_are_chosen_by_target(tmp_path, monkeypatch):
    nodes = {
        "features": {"_target_": f"{__name__}.GridFeatures", "max_keypoints": 50, "step": 16},
        "query_verification": {
            "_target_": "locretrieval.sfm.verification.PoseVerification",
            "max_epipolar_error": 2.0,
        },
    }
    plain = OmegaConf.to_container(helpers.compose_config("evaluate").sfm, resolve=True)
    settings = validated(
        SfmSettings, {**plain, **nodes, "workers": 1, "matching": {**plain["matching"], "device": "cpu"}}, "sfm"
    )
    assert isinstance(settings.features, GridFeatures) and settings.query_verification == PoseVerification(2.0)
    camera = Camera("PINHOLE", 200, 150, (150.0, 150.0, 100.0, 75.0))
    images = ImageSet(
        ["a.jpg", "b.jpg"], Path("/nonexistent"), [camera] * 2, np.tile([1.0, 0, 0, 0], (2, 1)), np.zeros((2, 3))
    )
    store = extract_features(images, settings.features, tmp_path, workers=1)
    assert len(store.keypoints(["a.jpg"])["a.jpg"]) == 50  # its budget, its keypoint order
    matcher = PairMatcher(images, store, images, store, settings.matching, tmp_path)
    matcher.ensure([("a.jpg", "b.jpg")], 1, settings.query_verification)
    np.testing.assert_array_equal(
        matcher.load([("a.jpg", "b.jpg")], settings.query_verification)[("a.jpg", "b.jpg")],
        np.tile(np.arange(50), (2, 1)).T,
    )
    wrong = {**plain, "features": {"_target_": "locretrieval.sfm.verification.NoVerification"}}
    with pytest.raises(
        ConfigError,
        match=r"sfm.features._target_: locretrieval.sfm.verification.NoVerification "
        r"is not a part of sfm.features: a part there is a LocalFeatures",
    ):
        validated(SfmSettings, wrong, "sfm")
    with pytest.raises(ConfigError, match=r"sfm.query_verification.max_eror: unknown key"):
        validated(SfmSettings, {**plain, "query_verification": {**nodes["query_verification"], "max_eror": 1}}, "sfm")


@pytest.mark.parametrize("level, shown", [(None, False), ("0", True)])
def test_pycolmap_logs_below_warnings_only_when_glog_is_asked_to(level, shown):
    """The project's processes set glog's default level to warnings (``GLOG_minloglevel=2``): no
    ``Creating SIFT CPU feature extractor`` line per extractor, unless the environment asks."""
    import os
    import subprocess
    import sys

    environment = {key: value for key, value in os.environ.items() if key != "GLOG_minloglevel"}
    if level is not None:
        environment["GLOG_minloglevel"] = level
    script = "import locretrieval, pycolmap\npycolmap.FeatureExtractor.create(pycolmap.FeatureExtractionOptions())"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=environment, timeout=120)
    assert done.returncode == 0, done.stderr
    assert ("Creating SIFT CPU feature extractor" in done.stderr) == shown
