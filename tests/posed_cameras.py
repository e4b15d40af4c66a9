"""Image sets of posed cameras built by hand, their frusta and their ground truths: the builders the
tests of frusta, chebyshev and groundtruth share (support module)."""

import numpy as np
from scipy.optimize import linprog
from scipy.spatial.transform import Rotation

from locretrieval import geometry
from locretrieval.frusta import TruncatedFrusta
from locretrieval.groundtruth import frustum_groundtruth as build_frustum
from locretrieval.groundtruth import relative_pose_groundtruth as build_relative_pose
from locretrieval.scene import Camera, ImageSet

# Square symmetric camera: half field of view 45 degrees (tan = 50 / 50).
WIDE = Camera("PINHOLE", 100, 100, (50.0, 50.0, 50.0, 50.0))


NEAR = 0.1


def relative_pose_groundtruth(
    database, queries, depth=50, position_threshold=25.0, rotation_threshold=45.0, ranked="all"
):
    """The relative-pose ground truth with the paper's thresholds unless given, every image ranked."""
    return build_relative_pose(
        database,
        queries,
        depth=depth,
        position_threshold=position_threshold,
        rotation_threshold=rotation_threshold,
        ranked=ranked,
    )


def frustum_groundtruth(database, queries, depth=50, near=NEAR, far=25.0, min_radius=0.0):
    return build_frustum(database, queries, depth=depth, near=near, far=far, min_radius=min_radius)


def about(axis: str, degrees: float) -> np.ndarray:
    """wxyz quaternion of a rotation by ``degrees`` about a coordinate axis."""
    x, y, z, w = Rotation.from_euler(axis, degrees, degrees=True).as_quat()
    return np.array([w, x, y, z])


def image_set(qvec, centers, cameras=None, prefix="img") -> ImageSet:
    """Images with world-to-camera rotations ``qvec`` at world ``centers`` (NaN: no pose)."""
    qvec = np.asarray(qvec, dtype=float).reshape(-1, 4)
    centers = np.asarray(centers, dtype=float).reshape(-1, 3)
    n = len(qvec)
    tvec = geometry.translations_from_centers(qvec, centers)
    return ImageSet([f"{prefix}/{i}.jpg" for i in range(n)], "/nonexistent", cameras or [WIDE] * n, qvec, tvec)


def linprog_radius(A: np.ndarray, b: np.ndarray) -> float:
    """Signed Chebyshev radius of ``A x <= b`` by scipy's HiGHS (rows of A unit-norm)."""
    G = np.hstack([A, np.linalg.norm(A, axis=1, keepdims=True)])
    solution = linprog([0.0, 0.0, 0.0, -1.0], A_ub=G, b_ub=b, bounds=[(None, None)] * 4, method="highs")
    assert solution.status == 0
    return -solution.fun


def random_cameras(rng: np.random.Generator, count: int, spread: float) -> ImageSet:
    """Random orientations, centres in a cube of side ``spread`` and varied intrinsics."""
    x, y, z, w = Rotation.random(count, random_state=rng.integers(1 << 31)).as_quat().T
    cameras = [
        Camera(
            "PINHOLE", 640, 480, (f, f * rng.uniform(0.9, 1.1), 320 + rng.uniform(-40, 40), 240 + rng.uniform(-30, 30))
        )
        for f in rng.uniform(250.0, 900.0, count)
    ]
    return image_set(np.stack([w, x, y, z], 1), rng.uniform(0, spread, (count, 3)), cameras)


def frusta(images: ImageSet, far: float) -> TruncatedFrusta:
    return TruncatedFrusta.of_images(images, np.arange(len(images)), NEAR, far)


def reference_radii(first: TruncatedFrusta, second: TruncatedFrusta) -> np.ndarray:
    """Signed linprog optimum of each pair's 12 half-spaces."""
    return np.array(
        [
            linprog_radius(np.concatenate([first.A[i], second.A[i]]), np.concatenate([first.b[i], second.b[i]]))
            for i in range(len(first))
        ]
    )
