"""Absolute pose from 2D-3D correspondences: pycolmap's LO-RANSAC P3P + non-linear refinement,
and the failure reasons shared by the SfM paradigms."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
import pycolmap
from locretrieval.localization.colmap_model import from_rigid3d, to_pycolmap_camera
from locretrieval.scene import Camera

DEFAULT_PNP: dict[str, Any] = {
    "max_error": 12.0,  # px: RANSAC inlier threshold (hloc's and pycolmap's default)
    "min_num_inliers": 12,  # fewer inliers: not localised
    "min_inlier_ratio": 0.01,  # RANSAC's lower bound on the inlier ratio (sets the trial count)
    "max_num_trials": 10000,
    "confidence": 0.99999,
    "random_seed": 0,  # deterministic RANSAC
}

#: Failure reasons (short fixed strings counted by the report).
EMPTY_RETRIEVAL = "empty retrieval"
NO_KEYPOINTS = "no keypoints"
TOO_FEW_IMAGES = "too few images"
NO_3D_POINTS = "no 3D points"
TOO_FEW_MATCHES = "too few matches"
PNP_FAILED = "pnp failed"
TOO_FEW_INLIERS = "too few inliers"


def pnp_settings(config: Mapping[str, Any] | None) -> dict[str, Any]:
    """PnP options with defaults filled in; unknown keys are an error."""
    settings = {**DEFAULT_PNP, **dict(config or {})}
    unknown = sorted(set(settings) - set(DEFAULT_PNP))
    if unknown:
        raise ValueError(f"unknown pnp settings {unknown}; known: {sorted(DEFAULT_PNP)}")
    return settings


def estimate_absolute_pose(
    points2D: np.ndarray, points3D: np.ndarray, camera: Camera, settings: Mapping[str, Any]
) -> tuple[np.ndarray, np.ndarray, int] | str:
    """World-to-camera ``(q wxyz, t, number of inliers)`` of a camera observing world points
    ``points3D [m, 3]`` at pixels ``points2D [m, 2]`` (COLMAP's pixel convention), or the
    failure reason."""
    minimum = max(4, int(settings["min_num_inliers"]))
    if len(points2D) < minimum:
        return TOO_FEW_MATCHES
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac.max_error = float(settings["max_error"])
    estimation.ransac.min_inlier_ratio = float(settings["min_inlier_ratio"])
    estimation.ransac.max_num_trials = int(settings["max_num_trials"])
    estimation.ransac.confidence = float(settings["confidence"])
    estimation.ransac.random_seed = int(settings["random_seed"])
    result = pycolmap.estimate_and_refine_absolute_pose(
        np.asarray(points2D, dtype=np.float64), np.asarray(points3D, dtype=np.float64),
        to_pycolmap_camera(camera), estimation, pycolmap.AbsolutePoseRefinementOptions(),
    )
    if result is None:
        return PNP_FAILED
    if int(result["num_inliers"]) < minimum:
        return TOO_FEW_INLIERS
    qvec, tvec = from_rigid3d(result["cam_from_world"])
    return qvec, tvec, int(result["num_inliers"])
