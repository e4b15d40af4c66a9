"""The relative-pose ground truth (`locretrieval.groundtruth.relative_pose`): scores, order, thresholds
and relevance."""

import numpy as np
import pytest
from omegaconf import OmegaConf
from posed_cameras import image_set, relative_pose_groundtruth

from locretrieval.groundtruth import relative_pose_groundtruth as build_relative_pose
from locretrieval.retrieval import EMPTY


def test_relative_pose_scores_order_and_relevance(pose_scene):
    database, queries = pose_scene
    gt = relative_pose_groundtruth(database, queries, depth=50)
    expected_s = {0: 10 / 25, 4: 5 / 25 + 20 / 45, 1: 30 / 45, 3: 30 / 25, 2: 20 / 25 + 60 / 45}
    assert gt.ranking.name == "gt_relative_pose" and gt.ranking.kind == "groundtruth"
    assert gt.ranking.indices[0].tolist() == [0, 4, 1, 3, 2]
    np.testing.assert_allclose(gt.ranking.scores[0], [-expected_s[i] for i in (0, 4, 1, 3, 2)], rtol=1e-6)
    assert gt.relevance[0].indices.tolist() == [0, 1, 4]
    # The query without a pose: no ranking, no relevance. The far query: ranked, none relevant.
    assert (gt.ranking.indices[1] == EMPTY).all() and gt.relevance[1].nnz == 0
    assert gt.ranking.lengths[2] == 5 and gt.relevance[2].nnz == 0
    assert gt.relevance.dtype == bool and gt.relevance.shape == (3, 5)


def test_relative_pose_ranks_only_images_within_the_thresholds_by_default(pose_scene):
    database, queries = pose_scene
    default = OmegaConf.load("configs/groundtruth/definitions/relative_pose.yaml").ranked
    gt = build_relative_pose(
        database, queries, depth=50, position_threshold=25.0, rotation_threshold=45.0, ranked=default
    )
    # the reference pairing: query 0 ranks its 3 relevant images by s (d0 0.4, d4 0.644, d1 0.667)
    assert gt.ranking.indices[0].tolist() == [0, 4, 1] + [EMPTY] * 2
    assert gt.ranking.lengths.tolist() == [3, 0, 0]  # the far query: nothing within 25 m and 45 deg
    assert (gt.relevance != relative_pose_groundtruth(database, queries).relevance).nnz == 0  # relevance unchanged
    with pytest.raises(ValueError, match="ranked: must be one of"):
        build_relative_pose(
            database, queries, depth=50, position_threshold=25.0, rotation_threshold=45.0, ranked="some"
        )


def test_relative_pose_thresholds_and_depth(pose_scene):
    database, queries = pose_scene
    gt = relative_pose_groundtruth(database, queries, depth=2, position_threshold=12.0, rotation_threshold=25.0)
    # s = c/12 + R/25: d0 0.833, d4 1.217, d1 1.2, d3 2.5, d2 4.07; relevant: c < 12 and R < 25.
    assert gt.ranking.indices[0].tolist() == [0, 1]
    assert gt.relevance[0].indices.tolist() == [0, 4]


def test_relative_pose_ignores_quaternion_signs(pose_scene):
    database, queries = pose_scene
    flipped_database = image_set(database.qvec, database.centers, prefix="db")
    flipped_queries = image_set(queries.qvec, queries.centers, prefix="q")
    flipped_database.qvec[:] = -database.qvec  # ImageSet normalises to w >= 0: force the sign back
    flipped_queries.qvec[:] = -queries.qvec
    a = relative_pose_groundtruth(database, queries)
    b = relative_pose_groundtruth(flipped_database, flipped_queries)
    np.testing.assert_array_equal(a.ranking.indices, b.ranking.indices)
    np.testing.assert_allclose(a.ranking.scores, b.ranking.scores, atol=1e-6)
    assert (a.relevance != b.relevance).nnz == 0
