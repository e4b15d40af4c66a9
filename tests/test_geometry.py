import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from locretrieval import geometry


def wxyz(rotation: Rotation) -> np.ndarray:
    x, y, z, w = rotation.as_quat().T
    return np.stack([w, x, y, z], -1)


def test_quaternion_matrix_round_trip_against_scipy():
    rotations = Rotation.random(200, random_state=1)
    q = wxyz(rotations)
    np.testing.assert_allclose(geometry.quaternion_to_matrix(q), rotations.as_matrix(), atol=1e-12)
    back = geometry.matrix_to_quaternion(rotations.as_matrix())
    assert np.all(back[:, 0] >= 0)
    np.testing.assert_allclose(np.abs(np.sum(back * q, axis=1)), 1.0, atol=1e-12)


def test_matrix_to_quaternion_half_turn():
    half_turn = np.diag([1.0, -1.0, -1.0])  # 180 degrees about x
    np.testing.assert_allclose(np.abs(geometry.matrix_to_quaternion(half_turn)), [0, 1, 0, 0], atol=1e-12)


def test_rotation_error_equals_hand_computed_angle():
    angle = np.radians(30.0)
    about_z = np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)])
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    assert geometry.rotation_errors_deg(identity, about_z) == pytest.approx(30.0, abs=1e-9)
    # Sign invariance: -q is the same rotation.
    assert geometry.rotation_errors_deg(identity, -about_z) == pytest.approx(30.0, abs=1e-9)
    assert geometry.rotation_errors_deg(about_z, -about_z) == pytest.approx(0.0, abs=1e-6)
    # The trace formula of the paper's eq. 4 on explicit matrices.
    R_est = geometry.quaternion_to_matrix(about_z)
    R_ref = np.array([[1.0, 0, 0], [0, np.cos(0.7), -np.sin(0.7)], [0, np.sin(0.7), np.cos(0.7)]])
    expected = np.degrees(np.arccos((np.trace(R_est.T @ R_ref) - 1) / 2))
    q_ref = geometry.matrix_to_quaternion(R_ref)
    assert geometry.rotation_errors_deg(about_z, q_ref) == pytest.approx(expected, abs=1e-9)


def test_pairwise_errors_equal_the_hand_computed_angles_and_distances_of_every_pair():
    angles = np.array([0.0, 1e-7, 0.5, 30.0, 90.0, 179.9, 180.0])  # degrees about z, and -q of each
    about_z = wxyz(Rotation.from_euler("z", angles[:, None], degrees=True))
    others = np.concatenate([about_z, -about_z, wxyz(Rotation.random(20, random_state=4))])
    rotation = geometry.pairwise_rotation_errors_deg(about_z, others)
    assert rotation.shape == (7, 34)
    expected = np.abs(angles[:, None] - angles[None])
    np.testing.assert_allclose(rotation[:, :7], expected, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(rotation[:, 7:14], expected, rtol=1e-6, atol=1e-9)  # -q is the same rotation
    relative = [
        [(Rotation.from_quat(a[[1, 2, 3, 0]]).inv() * Rotation.from_quat(b[[1, 2, 3, 0]])).magnitude() for b in others]
        for a in about_z
    ]
    np.testing.assert_allclose(rotation, np.degrees(relative), atol=1e-9)
    np.testing.assert_allclose(rotation, geometry.rotation_errors_deg(about_z[:, None], others[None]), atol=1e-9)
    centers = np.random.default_rng(0).normal(size=(9, 3))
    distances = geometry.pairwise_position_errors(centers[:4], centers)
    assert distances[1, 1] == 0.0 and distances[2, 5] == pytest.approx(np.sqrt(((centers[2] - centers[5]) ** 2).sum()))


def test_camera_center_and_position_error():
    q = wxyz(Rotation.from_euler("y", 90, degrees=True))
    R = Rotation.from_euler("y", 90, degrees=True).as_matrix()
    t = np.array([1.0, 2.0, 3.0])
    center = geometry.camera_centers(q, t)
    np.testing.assert_allclose(center, -R.T @ t, atol=1e-12)
    np.testing.assert_allclose(R @ center + t, 0.0, atol=1e-12)
    np.testing.assert_allclose(geometry.translations_from_centers(q, center), t, atol=1e-12)
    assert geometry.position_errors(center, center + [3.0, 4.0, 0.0]) == pytest.approx(5.0)


def test_compose_poses_matches_matrix_product():
    ra, rb = Rotation.random(2, random_state=3)
    ta, tb = np.array([1.0, -2.0, 0.5]), np.array([0.3, 0.1, 4.0])
    Ta, Tb = np.eye(4), np.eye(4)
    Ta[:3, :3], Ta[:3, 3] = ra.as_matrix(), ta
    Tb[:3, :3], Tb[:3, 3] = rb.as_matrix(), tb
    q, t = geometry.compose_poses(wxyz(ra), ta, wxyz(rb), tb)
    np.testing.assert_allclose(geometry.quaternion_to_matrix(q), (Ta @ Tb)[:3, :3], atol=1e-12)
    np.testing.assert_allclose(t, (Ta @ Tb)[:3, 3], atol=1e-12)


def test_average_quaternions_is_sign_invariant_and_weighted():
    angle = np.radians(20.0)
    plus = np.array([np.cos(angle / 2), 0, 0, np.sin(angle / 2)])
    minus = np.array([np.cos(angle / 2), 0, 0, -np.sin(angle / 2)])
    q = np.stack([plus, minus])
    mean = geometry.average_quaternions(q, np.array([0.5, 0.5]))
    np.testing.assert_allclose(mean, [1, 0, 0, 0], atol=1e-12)
    flipped = geometry.average_quaternions(np.stack([-plus, minus]), np.array([0.5, 0.5]))
    np.testing.assert_allclose(flipped, mean, atol=1e-12)
    np.testing.assert_allclose(geometry.average_quaternions(q, np.array([1.0, 0.0])), plus, atol=1e-12)


def test_frustum_halfspaces_contain_exactly_the_viewing_volume():
    rotation = Rotation.random(random_state=5)
    q, t = wxyz(rotation), np.array([0.5, -1.0, 2.0])
    intrinsics = np.array([300.0, 320.0, 160.0, 120.0, 320.0, 240.0])
    A, b = geometry.frustum_halfspaces(q, t, intrinsics, near=0.5, far=20.0)
    np.testing.assert_allclose(np.linalg.norm(A, axis=-1), 1.0)
    rng = np.random.default_rng(0)
    u, v = rng.uniform([0, 0], [320, 240], size=(500, 2)).T
    depth = rng.uniform(0.5, 20.0, size=500)
    cam = np.stack([(u - 160) / 300 * depth, (v - 120) / 320 * depth, depth], -1)
    world = (cam - t) @ rotation.as_matrix()  # R^T (x_cam - t)
    assert np.all(world @ A.T <= b + 1e-9)
    behind = (np.stack([cam[:, 0], cam[:, 1], -cam[:, 2]], -1) - t) @ rotation.as_matrix()
    beyond = (cam * (21.0 / depth[:, None]) - t) @ rotation.as_matrix()
    outside_u = (np.stack([(-5 - 160) / 300 * depth, cam[:, 1], depth], -1) - t) @ rotation.as_matrix()
    for points in (behind, beyond, outside_u):
        assert np.all((points @ A.T > b + 1e-9).any(axis=1))
    corners = geometry.frustum_corners(q, t, intrinsics, 0.5, 20.0)
    np.testing.assert_allclose((corners @ A.T - b).max(axis=1), 0.0, atol=1e-9)


def test_invalid_quaternion_rows():
    q = np.array([[1.0, 0, 0, 0], [np.nan, 0, 0, 0], [2.0, 0, 0, 0], [0.0, 0.6, 0.8, 0]])
    assert list(geometry.invalid_quaternion_rows(q)) == [1, 2]
