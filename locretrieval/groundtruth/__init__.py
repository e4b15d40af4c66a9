"""Ground-truth rankings and relevance (paper Sec. 3.6.3) and their statistics (Table 1)."""

from locretrieval.groundtruth.base import (
    AllRelevance,
    Definition,
    DefinitionContext,
    GroundTruth,
    RankedRelevance,
    RelevanceScope,
    groundtruth_from_scores,
    statistics_table,
)
from locretrieval.groundtruth.co_observation import CoObservationDefinition, co_observation_groundtruth
from locretrieval.groundtruth.compute import (
    GroundTruthSettings,
    compute_groundtruths,
    definition_type,
    parse_definition,
)
from locretrieval.groundtruth.frustum import FrustumDefinition, frustum_groundtruth
from locretrieval.groundtruth.relative_pose import (
    RelativePoseDefinition,
    relative_pose_groundtruth,
    relative_pose_scores,
)

__all__ = [
    "AllRelevance",
    "RankedRelevance",
    "RelevanceScope",
    "CoObservationDefinition",
    "Definition",
    "DefinitionContext",
    "FrustumDefinition",
    "GroundTruth",
    "GroundTruthSettings",
    "RelativePoseDefinition",
    "co_observation_groundtruth",
    "compute_groundtruths",
    "definition_type",
    "frustum_groundtruth",
    "groundtruth_from_scores",
    "parse_definition",
    "relative_pose_groundtruth",
    "relative_pose_scores",
    "statistics_table",
]
