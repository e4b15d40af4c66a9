"""Verification of matches (`locretrieval.sfm.verification`): by the known poses, two-view geometry, one
from outside the package."""

from dataclasses import dataclass
from pathlib import Path

import helpers
import numpy as np
import pytest
from local_features import (
    POSES,
    SFM,
    TWO_VIEW,
    GridFeatures,  # noqa: F401  (named by a _target_ of this module)
)
from omegaconf import OmegaConf
from scipy.spatial.transform import Rotation

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.scene import Camera, ImageSet, Scene
from locretrieval.sfm.features import extract_features
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.matching import PairMatcher
from locretrieval.sfm.verification import (
    NoVerification,
    PairVerification,
    PoseVerification,
    TwoViewVerification,
    VerificationBatch,
    essential_matrices,
    sampson_errors,
    two_view_inliers,
)


def geometric_error(x0: np.ndarray, x1: np.ndarray, q0, t0, q1, t1) -> float:
    """The gold-standard error: distance to the closest pair of exact projections of one
    3D point (optimal triangulation by least squares), in normalised coordinates."""
    from scipy.optimize import least_squares

    R0, R1 = geometry.quaternion_to_matrix(q0), geometry.quaternion_to_matrix(q1)

    def residuals(point):
        a, b = R0 @ point + t0, R1 @ point + t1
        return np.concatenate([a[:2] / a[2] - x0, b[:2] / b[2] - x1])

    start = np.linalg.solve(R0, np.append(x0, 1.0) * 6.0 - t0)
    return float(np.linalg.norm(least_squares(residuals, start, xtol=1e-15, ftol=1e-15).fun))


def test_sampson_error_approximates_the_geometric_error_and_bounds_matches_in_pixels():
    rng = np.random.default_rng(2)
    q0, q1 = (np.roll(Rotation.from_rotvec(rng.normal(0, 0.1, 3)).as_quat(), 1) for _ in range(2))
    t0, t1 = np.zeros(3), np.array([1.0, 0.1, 0.0])
    points = rng.uniform([-2, -2, 4], [2, 2, 8], (50, 3))
    cam0 = points @ geometry.quaternion_to_matrix(q0).T + t0
    cam1 = points @ geometry.quaternion_to_matrix(q1).T + t1
    x0, x1 = cam0[:, :2] / cam0[:, 2:], cam1[:, :2] / cam1[:, 2:]
    essential = essential_matrices(q0, t0, q1, t1)
    assert sampson_errors(x0, x1, essential).max() < 1e-10
    noisy = x1 + rng.normal(0, 0.004, x1.shape)
    expected = [geometric_error(a, b, q0, t0, q1, t1) for a, b in zip(x0[:10], noisy[:10])]
    np.testing.assert_allclose(sampson_errors(x0[:10], noisy[:10], essential), expected, rtol=0.02)
    # in pixels (f = 500): 25 exact matches, 25 moved 10 px off their epipolar line
    camera = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
    line = np.column_stack([x0, np.ones(50)]) @ essential.T
    normal = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    moved = np.where((np.arange(50) < 25)[:, None], x1, x1 + 0.02 * normal)
    matches = np.column_stack([np.arange(50), np.arange(50)])
    images = ImageSet(["a.jpg", "b.jpg"], Path("/nonexistent"), [camera] * 2, np.stack([q0, q1]), np.stack([t0, t1]))
    keypoints = {"a.jpg": x0 * 500 + [320, 240], "b.jpg": moved * 500 + [320, 240]}
    (kept,) = PoseVerification(2.0).verify(VerificationBatch(images, images, [(0, 1)], [matches], keypoints, keypoints))
    np.testing.assert_array_equal(kept, matches[:25])


def test_pose_verification_keeps_the_true_matches_by_the_rendered_depth(scene, tmp_path):
    """A raw match is true when the depth of the first image maps its keypoint onto the
    second; verification against the known poses keeps every true match and rejects only
    wrong ones (wrong matches along the epipolar line, e.g. on repeated floor tiles, remain)."""
    import kapture.io.records as kapture_records

    database = scene.database
    store = extract_features(database, SFM.features, tmp_path, workers=1)
    matcher = PairMatcher(database, store, database, store, SFM.matching, tmp_path)
    first, second = 1, 9  # looking across the corridor from neighbouring stations
    pair = (database.names[first], database.names[second])
    matcher.ensure([pair], workers=1, verification=POSES)
    raw = matcher.load([pair], NoVerification())[pair]
    verified = {tuple(m) for m in matcher.load([pair], POSES)[pair].tolist()}
    keypoints = store.keypoints(list(pair))
    camera = database.cameras[first]
    depth = kapture_records.depth_map_from_file(str(database.depth_paths[first]), (camera.width, camera.height))
    pixels = keypoints[pair[0]][raw[:, 0]]
    z = depth[pixels[:, 1].astype(int), pixels[:, 0].astype(int)]
    rays = np.column_stack([pixels, np.ones(len(pixels))]) @ np.linalg.inv(camera.calibration_matrix()).T
    R0, R1 = (geometry.quaternion_to_matrix(database.qvec[i]) for i in (first, second))
    world = (rays * z[:, None] - database.tvec[first]) @ R0
    projected = (world @ R1.T + database.tvec[second]) @ database.cameras[second].calibration_matrix().T
    error = np.linalg.norm(projected[:, :2] / projected[:, 2:] - keypoints[pair[1]][raw[:, 1]], axis=1)
    kept = np.array([tuple(m) in verified for m in raw.tolist()])
    true = error < 1.0
    assert true.sum() >= 15
    assert kept[true].all()
    assert (~kept).any() and (error[~kept] > 4.0).all()


def test_two_view_verification_keeps_raw_matches_consistent_with_the_poses(scene, tmp_path):
    database = scene.database
    store = extract_features(database, SFM.features, tmp_path, workers=1)
    matcher = PairMatcher(database, store, database, store, SFM.matching, tmp_path)
    first, second = 1, 9
    pair = (database.names[first], database.names[second])
    matcher.ensure([pair], workers=1, verification=TWO_VIEW)
    raw, verified = matcher.load([pair], NoVerification())[pair], matcher.load([pair], TWO_VIEW)[pair]
    assert len(verified) >= 15 and {tuple(m) for m in verified.tolist()} <= {tuple(m) for m in raw.tolist()}
    keypoints = store.keypoints(list(pair))
    batch = VerificationBatch(database, database, [(first, second)], [verified], keypoints, keypoints)
    (consistent,) = PoseVerification(4.0).verify(batch)
    assert len(consistent) > 0.9 * len(verified)


@pytest.mark.parametrize(
    "configuration, kept",
    [
        ("CALIBRATED", True),
        ("PLANAR_OR_PANORAMIC", True),
        ("WATERMARK", False),
        ("MULTIPLE", False),
        ("DEGENERATE", False),
    ],
)
def test_two_view_inliers_only_of_scene_geometries(configuration, kept, monkeypatch):
    import pycolmap

    class Result:
        config = int(getattr(pycolmap.TwoViewGeometryConfiguration, configuration))  # as pycolmap returns it
        inlier_matches = np.array([[3, 1], [0, 2]])

    monkeypatch.setattr(pycolmap, "estimate_two_view_geometry", lambda *args: Result())
    camera = Camera("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
    keypoints = np.zeros((10, 2))
    matches = np.array([[3, 1], [0, 2]] + [[i, i] for i in range(4, 10)])
    inliers = two_view_inliers(
        keypoints, keypoints, matches, camera, camera, TwoViewVerification(max_error=4.0, min_num_inliers=5)
    )
    np.testing.assert_array_equal(inliers, [0, 1] if kept else [])


@dataclass(unsafe_hash=True)
class FirstMatches(PairVerification):
    """A database verification from outside the package: each pair's first ``count`` matches."""

    count: int

    def store_name(self, images0, images1):
        return f"first-{self.count}"

    def verify(self, batch):
        return [matches[: self.count] for matches in batch.matches]


def test_a_database_verification_from_outside_the_package_is_chosen_through_the_config(tmp_path, monkeypatch):
    settings = helpers.sfm_settings(
        choices=[
            "~sfm.features",
            f"+sfm.features={{_target_: {__name__}.GridFeatures, max_keypoints: 50, step: 16}}",
            "~sfm.database_verification",
            f"+sfm.database_verification={{_target_: {__name__}.FirstMatches, count: 3}}",
        ]
    )
    assert settings.database_verification == FirstMatches(3)
    camera = Camera("PINHOLE", 200, 150, (150.0, 150.0, 100.0, 75.0))
    images = ImageSet(
        ["a.jpg", "b.jpg"], Path("/nonexistent"), [camera] * 2, np.tile([1.0, 0, 0, 0], (2, 1)), np.zeros((2, 3))
    )
    inputs = SfmInputs.prepare(Scene("grid", images, images.subset(np.arange(0))), settings, tmp_path)
    pair = ("a.jpg", "b.jpg")
    inputs.database_pairs.ensure([pair], 1, inputs.database_verification)
    np.testing.assert_array_equal(
        inputs.database_pairs.load([pair], inputs.database_verification)[pair], np.tile(np.arange(3), (2, 1)).T
    )
    default = helpers.sfm_settings().database_verification
    assert default == PoseVerification(
        OmegaConf.load(helpers.CONFIGS / "sfm/database_verification/poses.yaml").max_epipolar_error
    )
