"""A ranking's top k as pairs files (`locretrieval.export.pairs`)."""

import numpy as np

from locretrieval.export.pairs import ranked_pairs
from locretrieval.retrieval.ranking import Ranking


def test_ranked_pairs_keep_each_querys_order_and_leave_out_empty_slots():
    ranking = Ranking(
        "r", [[2, 0, -1], [-1, -1, -1], [1, 2, 0]], [[0.9, 0.5, 0], [0, 0, 0], [0.7, 0.6, 0.1]], "descriptor"
    )
    pairs = ranked_pairs(ranking, 2, ["q0", "q1", "q2"], ["d0", "d1", "d2"])
    assert [(q, d) for q, d, _ in pairs] == [("q0", "d2"), ("q0", "d0"), ("q2", "d1"), ("q2", "d2")]
    assert [s for _, _, s in pairs] == [float(np.float32(v)) for v in (0.9, 0.5, 0.7, 0.6)]
