"""Absolute pose from 2D-3D correspondences: pycolmap's LO-RANSAC P3P + non-linear refinement,
and the failure reasons shared by the SfM paradigms."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.config import require
from locretrieval.scene import Camera
from locretrieval.sfm.colmap_model import from_rigid3d, to_pycolmap_camera


@dataclass
class PnPSettings:
    """pycolmap LO-RANSAC P3P + refinement: inlier threshold ``max_error`` px; fewer than
    ``min_num_inliers`` inliers is not localised; ``min_inlier_ratio`` (sets the trial count),
    ``max_num_trials``, ``confidence`` and ``random_seed`` (deterministic RANSAC) as pycolmap's."""

    max_error: float
    min_num_inliers: int
    min_inlier_ratio: float
    max_num_trials: int
    confidence: float
    random_seed: int

    def __post_init__(self) -> None:
        require(self.max_error > 0, "max_error", f"must be a positive number of pixels, got {self.max_error}")
        require(
            self.min_num_inliers >= 4, "min_num_inliers", f"must be >= 4 (P3P and a check), got {self.min_num_inliers}"
        )
        require(0 < self.min_inlier_ratio <= 1, "min_inlier_ratio", f"must be in (0, 1], got {self.min_inlier_ratio}")
        require(self.max_num_trials >= 1, "max_num_trials", f"must be >= 1, got {self.max_num_trials}")
        require(0 < self.confidence < 1, "confidence", f"must be in (0, 1), got {self.confidence}")


#: Failure reasons (short fixed strings counted by the report).
EMPTY_RETRIEVAL = "empty retrieval"
NO_KEYPOINTS = "no keypoints"
TOO_FEW_IMAGES = "too few images"
NO_3D_POINTS = "no 3D points"
TOO_FEW_MATCHES = "too few matches"
PNP_FAILED = "pnp failed"
TOO_FEW_INLIERS = "too few inliers"


def estimate_absolute_pose(
    points2D: np.ndarray, points3D: np.ndarray, camera: Camera, settings: PnPSettings
) -> tuple[np.ndarray, np.ndarray, int] | str:
    """World-to-camera ``(q wxyz, t, number of inliers)`` of a camera observing world points
    ``points3D [m, 3]`` at pixels ``points2D [m, 2]`` (COLMAP's pixel convention), or the
    failure reason."""
    import pycolmap  # here: a run without SfM does not load it

    minimum = settings.min_num_inliers
    if len(points2D) < minimum:
        return TOO_FEW_MATCHES
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac.max_error = settings.max_error
    estimation.ransac.min_inlier_ratio = settings.min_inlier_ratio
    estimation.ransac.max_num_trials = settings.max_num_trials
    estimation.ransac.confidence = settings.confidence
    estimation.ransac.random_seed = settings.random_seed
    result = pycolmap.estimate_and_refine_absolute_pose(
        np.asarray(points2D, dtype=np.float64),
        np.asarray(points3D, dtype=np.float64),
        to_pycolmap_camera(camera),
        estimation,
        pycolmap.AbsolutePoseRefinementOptions(),
    )
    if result is None:
        return PNP_FAILED
    if int(result["num_inliers"]) < minimum:
        return TOO_FEW_INLIERS
    qvec, tvec = from_rigid3d(result["cam_from_world"])
    return qvec, tvec, int(result["num_inliers"])
