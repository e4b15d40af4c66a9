"""Relative camera pose ground truth (paper Sec. 3.6.3, "Relative camera pose")."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from locretrieval import geometry
from locretrieval.config import require
from locretrieval.groundtruth.base import DefinitionContext, GradedRows, GroundTruth, groundtruth_from_scores
from locretrieval.scene import ImageSet

#: Which database images a relative-pose ranking holds: only those within both thresholds (as
#: the reference pairing tool, kapture-localization's pose-based pairs) or every one.
RANKED = ("within_thresholds", "all")


@dataclass
class RelativePoseDefinition:
    """``position_threshold`` (tau_c, metres), ``rotation_threshold`` (tau_R, degrees) and which
    images are ``ranked`` (`RANKED`)."""

    position_threshold: float
    rotation_threshold: float
    ranked: str
    uses_sfm: ClassVar[bool] = False

    def __post_init__(self) -> None:
        require(
            self.position_threshold > 0, "position_threshold", f"must be positive metres, got {self.position_threshold}"
        )
        require(
            self.rotation_threshold > 0,
            "rotation_threshold",
            f"must be positive degrees, got {self.rotation_threshold}",
        )
        require(self.ranked in RANKED, "ranked", f"must be one of {list(RANKED)}, got {self.ranked!r}")

    def scores(self, images: ImageSet, rows: np.ndarray, others: ImageSet) -> tuple[np.ndarray, np.ndarray]:
        """``(s_rcp, relevant)``, each ``[len(rows), len(others)]``: the score of images ``rows``
        against every image of ``others`` (`relative_pose_scores`) and whether the pair is within
        both thresholds (strictly)."""
        score, position, rotation = relative_pose_scores(
            images.qvec[rows],
            images.centers[rows],
            others.qvec,
            others.centers,
            self.position_threshold,
            self.rotation_threshold,
        )
        return score, (position < self.position_threshold) & (rotation < self.rotation_threshold)

    def groundtruth(
        self, database: ImageSet, queries: ImageSet, depth: int, name: str, context: DefinitionContext
    ) -> GroundTruth:
        """Database images ranked by increasing ``s_rcp``, relevant within both thresholds.

        The thresholds play both roles the paper gives 25 m and 45 degrees: the normalisers
        ``tau_c`` and ``tau_R`` of the score, and the relevance criterion ``c_diff <
        position_threshold and R_diff < rotation_threshold``. The ranking stores the
        similarity ``-s_rcp`` (higher is better). ``ranked="within_thresholds"`` ranks only the
        relevant images, as the reference pairing tool does (a query with 3 relevant images has
        3, and paradigm 1 at larger k averages those 3); ``"all"`` ranks every database image, so
        a query with fewer relevant images than ``k`` gets its ``k`` closest ones.
        """

        def score_block(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            score, relevant = self.scores(queries, rows, database)
            rankable = relevant if self.ranked == "within_thresholds" else np.ones(score.shape, dtype=bool)
            return -score, rankable, relevant

        return groundtruth_from_scores(name, database, queries, depth, score_block)

    def graded(self, images: ImageSet, context: DefinitionContext) -> GradedRows:
        """``1 - s_rcp / 2`` within both thresholds (there ``s_rcp < 2``: in (0, 1]), else 0."""

        def grade(rows: np.ndarray) -> np.ndarray:
            score, relevant = self.scores(images, rows, images)
            return np.where(relevant, 1.0 - score / 2.0, 0.0)

        return grade


def relative_pose_scores(
    query_qvec: np.ndarray,
    query_centers: np.ndarray,
    database_qvec: np.ndarray,
    database_centers: np.ndarray,
    position_threshold: float,
    rotation_threshold: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``s_rcp = c_diff / tau_c + R_diff / tau_R`` for every query x database pair.

    Quaternions are wxyz of world-to-camera rotations (sign-invariant), centres in world
    coordinates (metres); ``tau_c = position_threshold`` (m), ``tau_R = rotation_threshold``
    (degrees). ``c_diff`` and ``R_diff`` are the paper's eq. 3-4.
    Returns ``(s, c_diff, R_diff)``, each ``[Q, N]``.
    """
    position = geometry.pairwise_position_errors(query_centers, database_centers)
    rotation = geometry.pairwise_rotation_errors_deg(query_qvec, database_qvec)
    return position / position_threshold + rotation / rotation_threshold, position, rotation


def relative_pose_groundtruth(
    database: ImageSet,
    queries: ImageSet,
    *,
    depth: int,
    position_threshold: float,
    rotation_threshold: float,
    ranked: str,
    name: str = "gt_relative_pose",
) -> GroundTruth:
    """`RelativePoseDefinition.groundtruth` of these parameters, by keyword."""
    definition = RelativePoseDefinition(position_threshold, rotation_threshold, ranked)
    return definition.groundtruth(database, queries, depth, name, DefinitionContext())
