"""Rankings (`locretrieval.retrieval.ranking`): the top k of scores, a seeded random ranking."""

import numpy as np
import pytest

from locretrieval.retrieval import EMPTY, random_ranking, top_k


def test_random_ranking_is_seeded_without_repeats_and_clamped():
    first, again, other = (random_ranking(20, 30, 10, seed) for seed in (0, 0, 1))
    assert first.kind == "baseline" and first.indices.shape == (20, 10)
    assert all(len(set(row)) == 10 for row in first.indices) and first.indices.max() < 30
    np.testing.assert_array_equal(first.indices, again.indices)
    assert (first.indices != other.indices).any()
    assert random_ranking(3, 4, 10, 0).depth == 4


@pytest.mark.parametrize("kind", ["continuous", "integer", "rounded_with_nan", "few_rankable"])
def test_top_k_takes_the_best_entries_ties_by_lower_index_also_when_a_tie_straddles_the_depth(kind):
    rng = np.random.default_rng(7)
    scores = {
        "continuous": rng.random((40, 300)),
        "integer": rng.integers(0, 4, (40, 300)).astype(float),  # ties at every depth
        "rounded_with_nan": np.where(rng.random((40, 300)) < 0.3, np.nan, np.round(rng.normal(size=(40, 300)), 1)),
        "few_rankable": rng.random((40, 300)),  # fewer rankable entries than the depth: EMPTY slots
    }[kind]
    valid = rng.random(scores.shape) < (0.05 if kind == "few_rankable" else 0.8)
    for depth in (1, 7, 50, 300):  # the partial selection below N / 4, the full sort above
        indices, top = top_k(scores, depth, valid)
        for row in range(len(scores)):
            ranked = sorted(
                (-scores[row, n], n) for n in range(scores.shape[1]) if valid[row, n] and np.isfinite(scores[row, n])
            )
            expected = [n for _, n in ranked[:depth]]
            assert indices[row].tolist() == expected + [EMPTY] * (depth - len(expected))
            np.testing.assert_array_equal(top[row, : len(expected)], scores[row, expected].astype(np.float32))
            assert (top[row, len(expected) :] == 0).all()
