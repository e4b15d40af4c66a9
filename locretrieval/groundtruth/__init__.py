"""Ground-truth rankings and relevance (paper Sec. 3.6.3) and their statistics (Table 1)."""

from locretrieval.groundtruth.base import GroundTruth, groundtruth_from_scores
from locretrieval.groundtruth.co_observation import co_observation_groundtruth
from locretrieval.groundtruth.compute import DEFINITIONS, compute_groundtruths
from locretrieval.groundtruth.frustum import TruncatedFrusta, frustum_groundtruth, overlap_radii
from locretrieval.groundtruth.relative_pose import relative_pose_groundtruth, relative_pose_scores

__all__ = [
    "DEFINITIONS",
    "GroundTruth",
    "TruncatedFrusta",
    "co_observation_groundtruth",
    "compute_groundtruths",
    "frustum_groundtruth",
    "groundtruth_from_scores",
    "overlap_radii",
    "relative_pose_groundtruth",
    "relative_pose_scores",
]
