"""Frustum-overlap ground truth (paper Sec. 3.6.3, "Overlap between the viewing frusta").

The score of a pair is the radius of the largest sphere inscribed in the intersection of
the two truncated viewing frusta (`locretrieval.frusta`, an exact linear program per pair).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from locretrieval.config import require
from locretrieval.frusta import TruncatedFrusta, pairwise_overlap_radii
from locretrieval.groundtruth.base import DefinitionContext, GradedRows, GroundTruth, groundtruth_from_scores
from locretrieval.scene import ImageSet


@dataclass
class FrustumDefinition:
    """Frusta truncated at ``near`` and ``far`` metres (``far`` ``None``: the scene's
    `Scene.frustum_far`); relevant when the overlap radius exceeds ``min_radius`` metres."""

    near: float
    far: float | None
    min_radius: float
    uses_sfm: ClassVar[bool] = False

    def __post_init__(self) -> None:
        require(self.near > 0, "near", f"must be a positive depth in metres, got {self.near}")
        require(self.far is None or self.far > self.near, "far", f"must exceed near ({self.near} m), got {self.far}")
        require(self.min_radius >= 0, "min_radius", f"must be >= 0 metres, got {self.min_radius}")

    def frusta(self, images: ImageSet, rows: np.ndarray, context: DefinitionContext) -> TruncatedFrusta:
        """The frusta of images ``rows``, truncated at ``near`` and ``far`` (``None``: the scene's)."""
        return TruncatedFrusta.of_images(images, rows, self.near, context.far_plane(self.far))

    def groundtruth(
        self, database: ImageSet, queries: ImageSet, depth: int, name: str, context: DefinitionContext
    ) -> GroundTruth:
        """Database images ranked by decreasing frustum-overlap radius (metres).

        Frusta are the pinhole viewing pyramids (distortion ignored) truncated at depths ``near``
        and ``far`` (``None``: the scene's) along the optical axis. Pairs whose frusta share no
        interior (radius 0) are never ranked; a pair is relevant when its radius exceeds
        ``min_radius``."""
        database_frusta = self.frusta(database, np.arange(len(database)), context)

        def score_block(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            radii = pairwise_overlap_radii(self.frusta(queries, rows, context), database_frusta)
            return radii, radii > 0, radii > self.min_radius

        return groundtruth_from_scores(name, database, queries, depth, score_block)

    def graded(self, images: ImageSet, context: DefinitionContext) -> GradedRows:
        """The overlap radius (metres) where it exceeds ``min_radius``, else 0."""
        frusta = self.frusta(images, np.arange(len(images)), context)

        def grade(rows: np.ndarray) -> np.ndarray:
            radii = pairwise_overlap_radii(frusta[rows], frusta)
            return np.where(radii > self.min_radius, radii, 0.0)

        return grade


def frustum_groundtruth(
    database: ImageSet,
    queries: ImageSet,
    *,
    depth: int,
    near: float,
    far: float,
    min_radius: float,
    name: str = "gt_frustum",
) -> GroundTruth:
    """`FrustumDefinition.groundtruth` of these parameters, by keyword."""
    return FrustumDefinition(near, far, min_radius).groundtruth(database, queries, depth, name, DefinitionContext())
