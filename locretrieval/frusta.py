"""Overlap of truncated viewing frusta: the radius of the largest sphere inside two of them.

The radius of a pair is an exact linear program (the Chebyshev centre of 12 half-spaces)
solved in batches by `locretrieval.chebyshev`. Two exact tests skip the pairs whose frusta
cannot overlap: their bounding spheres are apart, or all 8 corners of one frustum lie
outside a face plane of the other. Used by the frustum ground truth (paper Sec. 3.6.3) and
by the image-pair selection of the SfM maps (Sec. 3.9).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.distance import cdist

from locretrieval import geometry
from locretrieval.chebyshev import chebyshev_radius
from locretrieval.scene import ImageSet

#: Half-space order of `geometry.frustum_halfspaces`: left, right, top, bottom, near, far.
#: The near and far planes are opposite and parallel, so with left and top they form a
#: dual-feasible starting basis (the half-distance between near and far planes).
INITIAL_BASIS = np.array([4, 5, 0, 2])

#: Radii below this fraction of the frusta's size are rounding noise of touching frusta: 0.
ZERO_RADIUS = 1e-9


@dataclass(frozen=True)
class TruncatedFrusta:
    """World-space truncated viewing frusta ``A [n, 6, 3] x <= b [n, 6]`` (unit normals).

    ``corners [n, 8, 3]`` are their vertices; ``centers [n, 3]`` and ``radii [n]`` a
    bounding sphere of each (the corners' mean and the largest distance to it).
    """

    A: np.ndarray
    b: np.ndarray
    corners: np.ndarray
    centers: np.ndarray
    radii: np.ndarray

    @classmethod
    def of_images(cls, images: ImageSet, rows: np.ndarray, near: float, far: float) -> "TruncatedFrusta":
        """Frusta of the images at ``rows`` (world-to-camera poses, pinhole intrinsics)."""
        qvec, tvec, intrinsics = images.qvec[rows], images.tvec[rows], images.intrinsics[rows]
        A, b = geometry.frustum_halfspaces(qvec, tvec, intrinsics, near, far)
        corners = geometry.frustum_corners(qvec, tvec, intrinsics, near, far)
        centers = corners.mean(axis=1)
        radii = np.linalg.norm(corners - centers[:, None], axis=-1).max(axis=1)
        return cls(A, b, corners, centers, radii)

    def __len__(self) -> int:
        return len(self.A)

    def __getitem__(self, index: np.ndarray) -> "TruncatedFrusta":
        return TruncatedFrusta(
            self.A[index], self.b[index], self.corners[index], self.centers[index], self.radii[index]
        )


def may_overlap(first: TruncatedFrusta, second: TruncatedFrusta) -> np.ndarray:
    """Boolean ``[P]``: pairs ``(first[i], second[i])`` whose interiors may intersect.

    False only when overlap is impossible (up to rounding): the bounding spheres are
    apart, or a face plane of one frustum has every corner of the other on its outer side.
    """
    distance = np.linalg.norm(first.centers - second.centers, axis=-1)
    spheres_meet = distance <= first.radii + second.radii
    return spheres_meet & ~_face_separates(first, second) & ~_face_separates(second, first)


def _face_separates(faces: TruncatedFrusta, points: TruncatedFrusta) -> np.ndarray:
    """``[P]``: some face plane of ``faces[i]`` has all corners of ``points[i]`` outside."""
    signed = faces.A @ points.corners.transpose(0, 2, 1) - faces.b[:, :, None]  # [P, 6 faces, 8 corners]
    return (signed >= 0).all(axis=2).any(axis=1)


def overlap_radii(first: TruncatedFrusta, second: TruncatedFrusta) -> np.ndarray:
    """Radius ``[P]`` of the largest sphere inside ``first[i]`` and ``second[i]``.

    Exact (a certified linear-program optimum) for the pairs `may_overlap` keeps; 0 for
    the others, for empty intersections, and below ``ZERO_RADIUS`` times the larger
    bounding-sphere radius (intersections without interior, up to rounding).
    """
    radii = np.zeros(len(first))
    keep = np.flatnonzero(may_overlap(first, second))
    A = np.concatenate([first.A[keep], second.A[keep]], axis=1)
    b = np.concatenate([first.b[keep], second.b[keep]], axis=1)
    radii[keep] = chebyshev_radius(A, b, INITIAL_BASIS)
    noise = ZERO_RADIUS * np.maximum(first.radii, second.radii)
    return np.where(radii > noise, radii, 0.0)


def pairwise_overlap_radii(queries: TruncatedFrusta, database: TruncatedFrusta) -> np.ndarray:
    """Dense ``[Q, N]`` `overlap_radii` of every query x database pair (memory O(Q N): callers
    with large sets pass blocks of queries)."""
    meet = cdist(queries.centers, database.centers) <= queries.radii[:, None] + database.radii[None]
    rows, columns = np.nonzero(meet)
    radii = np.zeros(meet.shape)
    radii[rows, columns] = overlap_radii(queries[rows], database[columns])
    return radii
