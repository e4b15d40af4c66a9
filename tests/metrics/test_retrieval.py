"""Retrieval metrics (`locretrieval.metrics.retrieval`): P@k, R@k and mAP of rankings against relevance."""

import numpy as np
import pytest
from scipy import sparse

from locretrieval.metrics.retrieval import RETRIEVAL_COLUMNS, retrieval_metrics, retrieval_tables
from locretrieval.retrieval import EMPTY, Ranking, ranking_from_scores, relevant_hits
from locretrieval.scene import Camera, ImageSet

CAMERA = Camera("SIMPLE_PINHOLE", 64, 48, (50.0, 32.0, 24.0))


def relevance_matrix(rows: list[list[int]], num_database: int) -> sparse.csr_matrix:
    dense = np.zeros((len(rows), num_database), dtype=bool)
    for q, relevant in enumerate(rows):
        dense[q, relevant] = True
    return sparse.csr_matrix(dense)


# q0: relevant {1, 3}; q1: relevant {0} but never retrieved, short ranking; q2: a pose but no
# relevant image; q3: no reference pose (no relevance, empty ranking).
RELEVANCE = relevance_matrix([[1, 3], [0], [], []], 6)
INDICES = np.array([[3, 0, 1, 5], [2, 4, EMPTY, EMPTY], [0, 1, 2, 3], [EMPTY] * 4])
KS = [1, 2, 3, 4, 5]


def queries() -> ImageSet:
    q = np.tile([1.0, 0, 0, 0], (4, 1))
    t = np.zeros((4, 3))
    q[3] = t[3] = np.nan
    tags = [frozenset({"day"}), frozenset(), frozenset(), frozenset({"day", "night"})]
    return ImageSet([f"q{i}.png" for i in range(4)], "/x", [CAMERA] * 4, q, t, tags)


def test_per_query_metrics_match_hand_computed_values():
    metrics = retrieval_metrics(INDICES, RELEVANCE, KS)
    np.testing.assert_allclose(metrics["precision"][0], [1, 1 / 2, 2 / 3, 2 / 4, 2 / 5])  # k=5 > depth: empty slot
    np.testing.assert_allclose(metrics["recall"][0], [1, 1, 1, 1, 1])
    # AP@k = sum_{i<=k} P@i rel_i / min(R, k): (1) / 1, (1) / 2, (1 + 2/3) / 2, ...
    np.testing.assert_allclose(metrics["average_precision"][0], [1, 1 / 2, 5 / 6, 5 / 6, 5 / 6])
    np.testing.assert_array_equal(metrics["precision"][1], 0)
    np.testing.assert_array_equal(metrics["recall"][1], 0)
    np.testing.assert_array_equal(metrics["average_precision"][1], 0)
    np.testing.assert_array_equal(metrics["precision"][2], 0)
    assert np.isnan(metrics["average_precision"][2]).all()  # no relevant image: AP undefined


def test_a_perfect_ranking_has_average_precision_one_at_every_k():
    metrics = retrieval_metrics(np.array([[0, 1, 2, 3]]), relevance_matrix([[0, 1, 2]], 4), [1, 2, 3, 4])
    np.testing.assert_allclose(metrics["average_precision"][0], 1.0)
    np.testing.assert_allclose(metrics["precision"][0], [1, 1, 1, 3 / 4])


def test_ties_follow_the_stored_order_and_scores_are_ignored():
    relevance = relevance_matrix([[1]], 3)
    tied = ranking_from_scores("tied", np.array([[0.5, 0.5, 0.1]]), 3, "descriptor")
    assert tied.indices.tolist() == [[0, 1, 2]]  # top_k: lower database index first
    metrics = retrieval_metrics(tied.indices, relevance, [1, 2])
    np.testing.assert_allclose(metrics["precision"][0], [0, 1 / 2])
    np.testing.assert_allclose(metrics["average_precision"][0], [0, 1 / 2])
    swapped = Ranking("swapped", [[1, 0, 2]], [[0.5, 0.5, 0.1]], "descriptor")
    np.testing.assert_allclose(retrieval_metrics(swapped.indices, relevance, [1, 2])["precision"][0], [1, 1 / 2])


def test_relevant_hits_ignore_empty_slots():
    assert relevant_hits(INDICES, RELEVANCE).tolist() == [
        [True, False, True, False],
        [False, False, False, False],
        [False, False, False, False],
        [False, False, False, False],
    ]


def test_tables_average_over_queries_with_a_pose_and_count_them():
    ranking = Ranking("netvlad", INDICES, np.zeros(INDICES.shape), "descriptor")
    subsets = {"all": np.ones(4, bool), "day": np.array([1, 0, 0, 1], bool), "night": np.array([0, 0, 0, 1], bool)}
    table, per_query = retrieval_tables("toy", [ranking], {"gt_pose": RELEVANCE}, queries(), subsets, KS, [1, 3])
    assert list(table.columns) == RETRIEVAL_COLUMNS
    value = table.set_index(["subset", "metric", "k"])["value"]
    count = table.set_index(["subset", "metric", "k"])["num_queries"]
    assert value[("all", "precision", 1)] == pytest.approx(1 / 3)  # q0, q1, q2 (q3 has no pose)
    assert value[("all", "precision", 3)] == pytest.approx((2 / 3) / 3)
    assert value[("all", "recall", 4)] == pytest.approx(1 / 3)
    assert value[("all", "map", 3)] == pytest.approx((5 / 6 + 0) / 2)  # q2 has no relevant image
    assert count[("all", "precision", 1)] == 3 and count[("all", "map", 1)] == 2
    assert value[("day", "precision", 2)] == pytest.approx(1 / 2) and count[("day", "recall", 2)] == 1
    assert "night" not in set(table["subset"])  # its only query has no pose
    assert len(table) == 2 * 3 * len(KS)
    # per query: queries with a pose, k of the paradigms
    assert set(per_query["query"]) == {"q0.png", "q1.png", "q2.png"}
    assert sorted(per_query["k"].unique()) == [1, 3]
    row = per_query.set_index(["metric", "k", "query"])["value"]
    assert row[("precision", 3, "q0.png")] == pytest.approx(2 / 3)
    assert row[("average_precision", 3, "q0.png")] == pytest.approx(5 / 6)
    assert np.isnan(row[("average_precision", 1, "q2.png")])


def test_inconsistent_shapes_are_errors_naming_the_ground_truth():
    ranking = Ranking("netvlad", INDICES, np.zeros(INDICES.shape), "descriptor")
    with pytest.raises(ValueError, match="gt_small"):
        retrieval_tables("toy", [ranking], {"gt_small": RELEVANCE[:, :3]}, queries(), {"all": np.ones(4, bool)}, KS, KS)
    with pytest.raises(ValueError, match="gt_rows"):
        retrieval_tables("toy", [ranking], {"gt_rows": RELEVANCE[:3]}, queries(), {"all": np.ones(4, bool)}, KS, KS)
    with pytest.raises(ValueError, match=r"subset masks \{'night': 3\}"):
        retrieval_tables(
            "toy", [ranking], {"gt": RELEVANCE}, queries(), {"all": np.ones(4, bool), "night": np.ones(3, bool)}, KS, KS
        )
