"""The frustum-overlap ground truth (`locretrieval.groundtruth.frustum`)."""

import numpy as np
import pytest
from posed_cameras import NEAR, frusta, frustum_groundtruth, random_cameras, reference_radii, relative_pose_groundtruth

from locretrieval.frusta import TruncatedFrusta
from locretrieval.retrieval import EMPTY


def test_frustum_groundtruth_ranks_by_radius_and_skips_empty_pairs():
    rng = np.random.default_rng(2)
    database = random_cameras(rng, 40, 25.0)
    queries = random_cameras(rng, 6, 25.0)
    queries.qvec[4] = np.nan  # a query without a pose
    gt = frustum_groundtruth(database, queries, depth=10, far=15.0, min_radius=0.5)
    posed = np.flatnonzero(queries.has_pose)
    query_frusta = TruncatedFrusta.of_images(queries, posed, NEAR, 15.0)
    database_frusta = frusta(database, 15.0)
    for row, q in enumerate(posed):
        pairs = np.full(len(database), row)
        expected = np.maximum(reference_radii(query_frusta[pairs], database_frusta), 0.0)
        order = np.argsort(-expected, kind="stable")
        order = order[expected[order] > 1e-9][:10]
        assert gt.ranking.indices[q, : len(order)].tolist() == order.tolist()
        assert (gt.ranking.indices[q, len(order) :] == EMPTY).all()
        np.testing.assert_allclose(gt.ranking.scores[q, : len(order)], expected[order], rtol=1e-5)
        assert gt.relevance[q].indices.tolist() == np.flatnonzero(expected > 0.5).tolist()
    assert (gt.ranking.indices[4] == EMPTY).all() and gt.relevance[4].nnz == 0
    assert gt.relevance.nnz > 0 and (gt.ranking.lengths[posed] < 10).any()


def test_bad_planes_and_unposed_database_images_are_rejected(pose_scene):
    database, queries = pose_scene
    with pytest.raises(ValueError, match=r"far: must exceed near \(5.0 m\), got 2.0"):
        frustum_groundtruth(database, queries, near=5.0, far=2.0)
    database.tvec[3] = np.nan
    with pytest.raises(ValueError, match=r"database images without a pose: \['db/3.jpg'\]"):
        relative_pose_groundtruth(database, queries)
