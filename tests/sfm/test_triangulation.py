"""Triangulation with known poses (`locretrieval.sfm.triangulation`): exact tracks, an outlier dropped."""

import numpy as np
from scipy.spatial.transform import Rotation

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.scene import Camera
from locretrieval.sfm.triangulation import BatchedTriangulation, MapInput


def projected_views(points: np.ndarray, count: int, rng: np.random.Generator):
    """``count`` cameras on a circle of 10 m looking at ``points`` (world, around the origin, far
    from it: 1,000 m east) and each point's exact projection in every camera (COLMAP pixels)."""
    camera = Camera("PINHOLE", 640, 480, (400.0, 400.0, 320.0, 240.0))
    angles = np.linspace(-0.3, 0.3, count)
    centers = np.column_stack([1000.0 + 10 * np.sin(angles), 0.0 * angles, -10 * np.cos(angles)])
    qvec, tvec, keypoints = [], [], []
    for center, angle in zip(centers, angles):
        rotation = Rotation.from_euler("y", -angle).as_matrix()  # camera z towards the points
        x, y, z, w = Rotation.from_matrix(rotation).as_quat()
        qvec.append([w, x, y, z])
        tvec.append(-rotation @ center)
        in_camera = (points - 0.0) @ rotation.T + tvec[-1]
        keypoints.append(in_camera[:, :2] / in_camera[:, 2:] * 400.0 + [320.0, 240.0])
    return [camera] * count, np.array(qvec), np.array(tvec), keypoints


def test_batched_triangulation_solves_exact_tracks_and_drops_an_outlier_observation():
    rng = np.random.default_rng(2)
    points = np.column_stack([1000.0 + rng.uniform(-2, 2, 50), rng.uniform(-1, 1, 50), rng.uniform(3, 6, 50)])
    cameras, qvec, tvec, keypoints = projected_views(points, 4, rng)
    keypoints[2][7] += [30.0, -20.0]  # one observation of point 7 off by 36 px
    every = np.column_stack([np.arange(50), np.arange(50)])
    matches = {(a, b): every for a in range(4) for b in range(a + 1, 4)}
    batched = BatchedTriangulation(min_angle=1.5, max_reprojection_error=4.0)
    sparse_map = batched.triangulate(cameras, qvec, tvec, keypoints, matches)
    assert sparse_map.num_points == 50
    order = sparse_map.observations[0]  # image 0 sees every point
    np.testing.assert_allclose(
        sparse_map.points[order], points, atol=1e-6
    )  # 1,000 m from the origin: solved near the cameras
    assert sparse_map.observations[2][7] == -1 and (sparse_map.observations[2][np.arange(50) != 7] >= 0).all()
    # two views: points whose two rays meet at less than min_angle are dropped
    centers = geometry.camera_centers(qvec[:2], tvec[:2])
    rays = [(points - center) / np.linalg.norm(points - center, axis=1, keepdims=True) for center in centers]
    angles = np.degrees(np.arccos(np.einsum("pi,pi->p", *rays)))
    threshold = float(np.median(angles))
    two_views = BatchedTriangulation(min_angle=threshold, max_reprojection_error=4.0)
    narrow = two_views.triangulate(cameras[:2], qvec[:2], tvec[:2], keypoints[:2], {(0, 1): every})
    np.testing.assert_array_equal(narrow.observations[0] >= 0, angles >= threshold)
    # several maps in one call: each the map it is alone, bit for bit
    other = (cameras[:3], qvec[:3], tvec[:3], keypoints[:3], {(0, 1): every[:20], (1, 2): every[10:40]})
    together = batched.triangulate_many([MapInput(*other), MapInput(cameras, qvec, tvec, keypoints, matches)])
    for alone, joint in zip([batched.triangulate(*other), sparse_map], together):
        np.testing.assert_array_equal(alone.points, joint.points)
        for a, b in zip(alone.observations, joint.observations):
            np.testing.assert_array_equal(a, b)
