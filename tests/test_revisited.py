import pickle

import numpy as np
import pytest

from locretrieval.metrics.revisited import REVISITED_COLUMNS, evaluate_revisited, load_revisited_groundtruth
from locretrieval.retrieval import EMPTY, Ranking

# 8 database images, 2 queries.
# q0: easy {0, 3}, hard {5}, junk {1}; ranking 1 0 2 5 3 4 6 7.
# q1: easy {}, hard {2}, junk {}; ranking 2 0 1 3 4 5 6 7.
GROUNDTRUTH = {
    "imlist": [f"db{i}" for i in range(8)],
    "qimlist": ["q0", "q1"],
    "gnd": [
        {"easy": [0, 3], "hard": [5], "junk": [1], "bbx": [0, 0, 10, 10]},
        {"easy": [], "hard": [2], "junk": [], "bbx": [0, 0, 10, 10]},
    ],
}
RANKING = np.array([[1, 0, 2, 5, 3, 4, 6, 7], [2, 0, 1, 3, 4, 5, 6, 7]])


@pytest.fixture
def groundtruth(tmp_path):
    path = tmp_path / "gnd_toy.pkl"
    path.write_bytes(pickle.dumps(GROUNDTRUTH))
    return load_revisited_groundtruth(path)


def test_protocols_match_hand_computed_values(groundtruth):
    table = evaluate_revisited(Ranking("toy", RANKING, np.zeros(RANKING.shape), "descriptor"), groundtruth, "toy", kappas=(1, 5, 10))
    assert list(table.columns) == REVISITED_COLUMNS
    value = table.set_index(["protocol", "metric", "k"])["value"]
    count = table.set_index(["protocol", "metric", "k"])["num_queries"]
    # Medium, q0: positives {0, 3, 5}, junk {1}: without junk the order is 0 2 5 3 4 6 7,
    # positives at ranks 0, 2, 3 -> AP = (1 + (1/2 + 2/3)/2 + (2/3 + 3/4)/2) / 3 = 55/72.
    assert value[("medium", "map", 0)] == pytest.approx((55 / 72 + 1.0) / 2)  # q1: hard {2} ranked first
    # Easy, q0: positives {0, 3}, junk {1, 5}: order 0 2 3 4 6 7 -> ranks 0, 2 -> 19/24; q1 has no
    # easy positive and is left out.
    assert value[("easy", "map", 0)] == pytest.approx(19 / 24) and count[("easy", "map", 0)] == 1
    # Hard, q0: positive {5}, junk {1, 0, 3}: order 2 5 4 6 7 -> rank 1 -> (0/1 + 1/2)/2 = 1/4.
    assert value[("hard", "map", 0)] == pytest.approx((1 / 4 + 1.0) / 2) and count[("hard", "map", 0)] == 2
    # mP@k: k' = min(k, 1-based position of the last positive). Medium q0: positives at
    # 1, 3, 4 -> P@1 = 1, P@5 = P@10 = 3/4 (k' = 4); q1: positive at 1 -> 1, 1, 1.
    assert value[("medium", "mp", 1)] == pytest.approx(1.0)
    assert value[("medium", "mp", 5)] == pytest.approx((3 / 4 + 1) / 2)
    assert value[("medium", "mp", 10)] == pytest.approx((3 / 4 + 1) / 2)
    # Hard q0: positive at 2 -> P@1 = 0/1, P@5 = 1/2.
    assert value[("hard", "mp", 1)] == pytest.approx((0 + 1) / 2)
    assert value[("hard", "mp", 5)] == pytest.approx((1 / 2 + 1) / 2)


def test_a_truncated_ranking_counts_missing_positives_as_not_retrieved(groundtruth):
    truncated = Ranking("toy", [[1, 0, 2, EMPTY], [0, 1, 3, EMPTY]], np.zeros((2, 4)), "descriptor")
    value = evaluate_revisited(truncated, groundtruth, "toy").set_index(["protocol", "metric", "k"])["value"]
    # Medium q0: only positive 0 retrieved (rank 0 after junk) of 3 -> AP 1/3; q1: positive 2
    # not retrieved -> AP 0, P@k 0.
    assert value[("medium", "map", 0)] == pytest.approx((1 / 3 + 0) / 2)
    assert value[("medium", "mp", 1)] == pytest.approx((1 + 0) / 2)


def test_malformed_files_are_reported_with_their_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="gnd_roxford5k.pkl"):
        load_revisited_groundtruth(tmp_path / "missing.pkl")
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(pickle.dumps({"imlist": [], "gnd": []}))
    with pytest.raises(ValueError, match="bad.pkl.*qimlist"):
        load_revisited_groundtruth(bad)
    outside = tmp_path / "outside.pkl"
    outside.write_bytes(pickle.dumps({**GROUNDTRUTH, "imlist": ["db0", "db1"]}))
    with pytest.raises(ValueError, match="outside.pkl.*q0"):
        load_revisited_groundtruth(outside)
