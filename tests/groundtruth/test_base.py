"""What every ground truth shares (`locretrieval.groundtruth.base`): statistics over the posed queries,
rankings of posed queries only, chunked scoring."""

import numpy as np
import pytest
from posed_cameras import frustum_groundtruth, relative_pose_groundtruth

from locretrieval.groundtruth import (
    GroundTruth,
    base,
)


def test_statistics_count_all_relevant_images_over_posed_queries(pose_scene):
    database, queries = pose_scene
    statistics = relative_pose_groundtruth(database, queries, depth=2).statistics()
    # Query 0: 3 relevant, 2 of them in its top 2 (d0, d4); query 2: none; query 1: no pose.
    assert statistics == {
        "queries": 3,
        "queries_without_pose": 1,
        "depth": 2,
        "avg_relevant": 1.5,
        "avg_relevant_in_ranking": 1.0,
        "missing_pct": 50.0,
    }


def test_statistics_without_any_posed_query(pose_scene):
    database, queries = pose_scene
    statistics = relative_pose_groundtruth(database, queries.subset([1])).statistics()
    assert statistics["queries_without_pose"] == 1 and np.isnan(statistics["avg_relevant"])


def test_groundtruth_rejects_rankings_for_queries_without_pose(pose_scene):
    database, queries = pose_scene
    gt = relative_pose_groundtruth(database, queries)
    with pytest.raises(ValueError, match="without a pose"):
        GroundTruth(gt.ranking, gt.relevance, np.array([True, True, False]))


def test_chunked_scoring_equals_one_chunk(pose_scene, monkeypatch):
    database, queries = pose_scene
    whole = frustum_groundtruth(database, queries, far=30.0)
    monkeypatch.setattr(base, "PAIRS_PER_CHUNK", 1)  # one query per chunk
    chunked = frustum_groundtruth(database, queries, far=30.0)
    np.testing.assert_array_equal(chunked.ranking.indices, whole.ranking.indices)
    np.testing.assert_array_equal(chunked.ranking.scores, whole.ranking.scores)
    assert (chunked.relevance != whole.relevance).nnz == 0
