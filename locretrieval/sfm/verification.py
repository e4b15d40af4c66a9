"""Geometric verification of the matches of image pairs: which matches a pair keeps.

A verification is an object chosen by ``_target_``: ``sfm.query_verification`` of
query-database pairs, ``sfm.database_verification`` of database pairs, whose poses are known
(`PoseVerification`):

- `NoVerification`: the raw matches (PnP's RANSAC rejects outliers later);
- `PoseVerification`: both images have known poses: matches whose Sampson error against the
  pose-derived essential matrix (undistorted coordinates, scaled to pixels by the mean focal
  length) is at most ``max_epipolar_error`` pixels. Exact and cheap, no RANSAC: a whole batch of
  pairs is verified at once, each image's keypoints undistorted once for all its pairs;
- `TwoViewVerification`: pycolmap's two-view geometry estimation (RANSAC on E, F and H), as the
  reference registrator verifies query pairs. About 30 ms per pair, ten times the matching.

Each writes its own store of verified matches (`PairVerification.store_name`), so a pair verified
two ways is matched once. Adding one: a class with ``store_name`` and ``verify`` and a YAML.
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.cache import config_key
from locretrieval.config import require
from locretrieval.scene import Camera, ImageSet

#: pycolmap two-view configurations whose inliers follow a scene geometry; the others are
#: undefined, degenerate, a watermark (a fixed image overlay) or several motions.
GEOMETRIC_CONFIGURATIONS = ("CALIBRATED", "UNCALIBRATED", "PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC")

Pair = tuple[str, str]


@dataclass
class VerificationBatch:
    """What verifying a batch of pairs reads: the two image sets (cameras, world-to-camera poses,
    q wxyz), the pairs as indices ``(i in images0, j in images1)``, their raw matches and the
    keypoints ``float32 [n, 2]`` of the images involved by name."""

    images0: ImageSet
    images1: ImageSet
    pairs: list[tuple[int, int]]
    matches: list[np.ndarray]
    keypoints0: Mapping[str, np.ndarray]
    keypoints1: Mapping[str, np.ndarray]


class PairVerification(abc.ABC):
    """Keeps the geometrically consistent matches of image pairs."""

    @abc.abstractmethod
    def store_name(self, images0: ImageSet, images1: ImageSet) -> str:
        """The suffix of its verified matches' store: everything the outcome depends on beyond
        the raw matches (its settings, the poses it reads)."""

    @abc.abstractmethod
    def verify(self, batch: VerificationBatch) -> list[np.ndarray]:
        """The rows of each pair's matches that it keeps, in order."""

    @property
    def needs_keypoints(self) -> bool:
        return True


@dataclass(unsafe_hash=True)  # hashable: the key of its store (never changed once built)
class NoVerification(PairVerification):
    """The raw matches, unverified."""

    def store_name(self, images0: ImageSet, images1: ImageSet) -> str:
        return "raw"

    def verify(self, batch: VerificationBatch) -> list[np.ndarray]:
        return list(batch.matches)

    @property
    def needs_keypoints(self) -> bool:
        return False


@dataclass(unsafe_hash=True)  # hashable: the key of its store (never changed once built)
class PoseVerification(PairVerification):
    """Matches within ``max_epipolar_error`` pixels (Sampson error) of the epipolar geometry of
    the two images' known poses."""

    max_epipolar_error: float

    def __post_init__(self) -> None:
        require(
            self.max_epipolar_error > 0,
            "max_epipolar_error",
            f"must be a positive number of pixels, got {self.max_epipolar_error}",
        )

    def store_name(self, images0: ImageSet, images1: ImageSet) -> str:
        return f"poses-{config_key(self.max_epipolar_error, images0.fingerprint(), images1.fingerprint())}"

    def verify(self, batch: VerificationBatch) -> list[np.ndarray]:
        images0, images1 = batch.images0, batch.images1
        first = sorted({i for i, _ in batch.pairs})
        second = sorted({j for _, j in batch.pairs})
        undistorted0 = {i: undistorted(images0.cameras[i], batch.keypoints0[images0.names[i]]) for i in first}
        undistorted1 = {j: undistorted(images1.cameras[j], batch.keypoints1[images1.names[j]]) for j in second}
        rows, columns = (
            np.array([i for i, _ in batch.pairs], dtype=np.int64),
            np.array([j for _, j in batch.pairs], dtype=np.int64),
        )
        essentials = essential_matrices(
            images0.qvec[rows], images0.tvec[rows], images1.qvec[columns], images1.tvec[columns]
        )
        kept = []
        for (i, j), matches, essential in zip(batch.pairs, batch.matches, essentials):
            points0, focal0 = undistorted0[i]
            points1, focal1 = undistorted1[j]
            errors = sampson_errors(points0[matches[:, 0]], points1[matches[:, 1]], essential)
            kept.append(matches[np.isfinite(errors) & (errors * 0.5 * (focal0 + focal1) <= self.max_epipolar_error)])
        return kept


@dataclass(unsafe_hash=True)  # hashable: the key of its store (never changed once built)
class TwoViewVerification(PairVerification):
    """pycolmap's two-view geometry (RANSAC ``max_error`` px, at least ``min_num_inliers``)."""

    max_error: float
    min_num_inliers: int

    def __post_init__(self) -> None:
        require(self.max_error > 0, "max_error", f"must be a positive number of pixels, got {self.max_error}")
        require(
            self.min_num_inliers >= 5, "min_num_inliers", f"must be >= 5 (a minimal sample), got {self.min_num_inliers}"
        )

    def store_name(self, images0: ImageSet, images1: ImageSet) -> str:
        return f"two-view-{config_key(dataclasses.asdict(self))}"

    def verify(self, batch: VerificationBatch) -> list[np.ndarray]:
        images0, images1 = batch.images0, batch.images1
        return [
            matches[
                two_view_inliers(
                    batch.keypoints0[images0.names[i]],
                    batch.keypoints1[images1.names[j]],
                    matches,
                    images0.cameras[i],
                    images1.cameras[j],
                    self,
                )
            ]
            for (i, j), matches in zip(batch.pairs, batch.matches)
        ]


def undistorted(camera: Camera, keypoints: np.ndarray) -> tuple[np.ndarray, float]:
    """Normalised, undistorted coordinates ``[n, 2]`` of pixel keypoints (COLMAP convention) and
    the camera's mean focal length (px)."""
    from locretrieval.sfm.colmap_model import to_pycolmap_camera

    converted = to_pycolmap_camera(camera)
    return converted.cam_from_img(np.asarray(keypoints, dtype=np.float64)).reshape(-1, 2), converted.mean_focal_length()


def essential_matrices(q0: np.ndarray, t0: np.ndarray, q1: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """``E = [t]x R`` ``[..., 3, 3]`` of camera 1 relative to camera 0 (world-to-camera poses, q
    wxyz): ``x1^T E x0 = 0`` for normalised image coordinates of one world point."""
    r0, r1 = geometry.quaternion_to_matrix(q0), geometry.quaternion_to_matrix(q1)
    rotation = r1 @ np.swapaxes(r0, -1, -2)
    t = np.asarray(t1) - np.einsum("...ij,...j->...i", rotation, np.asarray(t0))
    zero = np.zeros(t.shape[:-1])
    skew = np.stack(
        [
            np.stack([zero, -t[..., 2], t[..., 1]], -1),
            np.stack([t[..., 2], zero, -t[..., 0]], -1),
            np.stack([-t[..., 1], t[..., 0], zero], -1),
        ],
        -2,
    )
    return skew @ rotation


def sampson_errors(points0: np.ndarray, points1: np.ndarray, essential: np.ndarray) -> np.ndarray:
    """Sampson distances ``[m]`` of normalised correspondences (same unit as the coordinates)."""
    x0 = np.column_stack([points0, np.ones(len(points0))])
    x1 = np.column_stack([points1, np.ones(len(points1))])
    line1 = x0 @ essential.T  # E x0
    line0 = x1 @ essential  # E^T x1
    numerator = np.einsum("ij,ij->i", x1, line1) ** 2
    denominator = line1[:, 0] ** 2 + line1[:, 1] ** 2 + line0[:, 0] ** 2 + line0[:, 1] ** 2
    return np.sqrt(numerator / np.maximum(denominator, np.finfo(float).tiny))


def two_view_inliers(
    keypoints0: np.ndarray,
    keypoints1: np.ndarray,
    matches: np.ndarray,
    camera0: Camera,
    camera1: Camera,
    settings: TwoViewVerification,
) -> np.ndarray:
    """Indices ``int32 [i]`` into ``matches`` of pycolmap's two-view geometry inliers (none
    unless the geometry is one of `GEOMETRIC_CONFIGURATIONS` with ``min_num_inliers``)."""
    import pycolmap

    from locretrieval.sfm.colmap_model import to_pycolmap_camera

    if len(matches) < settings.min_num_inliers:
        return np.empty(0, dtype=np.int32)
    options = pycolmap.TwoViewGeometryOptions()
    options.min_num_inliers = settings.min_num_inliers
    options.ransac.max_error = settings.max_error
    options.ransac.random_seed = 0
    result = pycolmap.estimate_two_view_geometry(
        to_pycolmap_camera(camera0),
        keypoints0.astype(np.float64),
        to_pycolmap_camera(camera1),
        keypoints1.astype(np.float64),
        np.asarray(matches, dtype=np.uint32),
        options,
    )
    inliers = np.asarray(result.inlier_matches, dtype=np.int64).reshape(-1, 2)
    configuration = pycolmap.TwoViewGeometryConfiguration(int(result.config)).name  # an int in the result
    if configuration not in GEOMETRIC_CONFIGURATIONS or not len(inliers):
        return np.empty(0, dtype=np.int32)
    # map inlier keypoint pairs back to rows of `matches`
    row_of = {(int(a), int(b)): row for row, (a, b) in enumerate(matches)}
    return np.array(sorted(row_of[(int(a), int(b))] for a, b in inliers), dtype=np.int32)


def verify_pairs(verification: PairVerification, batch: VerificationBatch) -> list[np.ndarray]:
    """``verification.verify(batch)``, with pairs without matches kept empty without work."""
    busy = [n for n, matches in enumerate(batch.matches) if len(matches)]
    kept = [matches[:0] for matches in batch.matches]
    if busy:
        subset = dataclasses.replace(
            batch, pairs=[batch.pairs[n] for n in busy], matches=[batch.matches[n] for n in busy]
        )
        for n, rows in zip(busy, verification.verify(subset)):
            kept[n] = rows
    return kept


def pair_indices(images0: ImageSet, images1: ImageSet, pairs: Sequence[Pair]) -> list[tuple[int, int]]:
    """``(i, j)`` of each name pair."""
    index0 = {name: i for i, name in enumerate(images0.names)}
    index1 = index0 if images1 is images0 else {name: j for j, name in enumerate(images1.names)}
    return [(index0[a], index1[b]) for a, b in pairs]
