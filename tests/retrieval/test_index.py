"""The faiss search of descriptors (`locretrieval.retrieval.index`): equal to brute force, ties by
database index, the own image excluded, the depth clamped, errors named."""

import logging

import numpy as np
import pytest

from locretrieval.retrieval.index import search


def unit_rows(rng: np.random.Generator, rows: int, dim: int) -> np.ndarray:
    values = rng.normal(size=(rows, dim)).astype(np.float32)
    return values / np.linalg.norm(values, axis=1, keepdims=True)


def brute_force(queries: np.ndarray, database: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray]:
    scores = queries.astype(np.float64) @ database.astype(np.float64).T
    order = np.argsort(-scores, axis=1, kind="stable")[:, :depth]
    return order, np.take_along_axis(scores, order, axis=1)


def ranked(depth: int = 5, chunk_size: int = 256) -> dict:
    """`search`'s depth, ranking name and chunk size of these tests."""
    return {"depth": depth, "name": "test", "chunk_size": chunk_size}


@pytest.mark.parametrize("chunk_size", [7, 37, 1000])
def test_search_equals_brute_force(chunk_size):
    rng = np.random.default_rng(0)
    queries, database = unit_rows(rng, 37, 16), unit_rows(rng, 120, 16)
    ranking = search(queries, database, depth=20, name="random", chunk_size=chunk_size)
    indices, scores = brute_force(queries, database, 20)
    np.testing.assert_array_equal(ranking.indices, indices)
    np.testing.assert_allclose(ranking.scores, scores, atol=1e-5)
    assert ranking.kind == "descriptor" and ranking.name == "random"
    np.testing.assert_array_equal(ranking.query_descriptors, queries)
    np.testing.assert_array_equal(ranking.database_descriptors, database)


def test_search_orders_ties_by_database_index():
    database = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 0.0]], dtype=np.float32)
    ranking = search(np.array([[1.0, 0.0]], dtype=np.float32), database, **ranked(depth=4))
    np.testing.assert_array_equal(ranking.indices, [[0, 2, 3, 1]])


@pytest.mark.parametrize("chunk_size", [5, 64])
def test_exclude_self_drops_exactly_the_own_index(chunk_size):
    rng = np.random.default_rng(1)
    descriptors = unit_rows(rng, 30, 8)
    descriptors[10] = descriptors[3]  # a duplicate: both tie at score 1 with each other
    ranking = search(descriptors, descriptors, **ranked(depth=6, chunk_size=chunk_size), exclude_self=True)
    assert ranking.indices.shape == (30, 6)
    assert not (ranking.indices == np.arange(30)[:, None]).any()
    scores = descriptors.astype(np.float64) @ descriptors.astype(np.float64).T
    np.fill_diagonal(scores, -np.inf)
    expected_scores = -np.sort(-scores, axis=1)[:, :6]
    np.testing.assert_allclose(ranking.scores, expected_scores, atol=1e-5)
    # Each slot holds the image its score belongs to (the duplicate may tie at the last slot).
    np.testing.assert_allclose(np.take_along_axis(scores, ranking.indices, axis=1), ranking.scores, atol=1e-5)
    assert ranking.indices[3, 0] == 10 and ranking.indices[10, 0] == 3
    np.testing.assert_allclose(ranking.scores[[3, 10], 0], 1.0, atol=1e-6)


def test_exclude_self_when_duplicates_crowd_out_the_own_index():
    # Five identical rows: faiss may return the others before row i; i must still be dropped.
    descriptors = np.tile(np.array([[0.6, 0.8]], dtype=np.float32), (5, 1))
    ranking = search(descriptors, descriptors, **ranked(depth=2), exclude_self=True)
    assert ranking.indices.shape == (5, 2)
    assert not (ranking.indices == np.arange(5)[:, None]).any()
    assert all(len(set(row)) == 2 for row in ranking.indices.tolist())


def test_depth_is_clamped_with_a_warning(caplog):
    rng = np.random.default_rng(2)
    database = unit_rows(rng, 5, 4)
    with caplog.at_level(logging.WARNING):
        ranking = search(unit_rows(rng, 3, 4), database, **ranked(depth=50))
    assert ranking.indices.shape == (3, 5)
    assert (ranking.indices >= 0).all()
    assert np.array_equal(np.sort(ranking.indices, axis=1), np.tile(np.arange(5), (3, 1)))
    assert "clamped to 5" in caplog.text
    assert search(database, database, **ranked(depth=50), exclude_self=True).indices.shape == (5, 4)


def test_search_errors_name_the_problem():
    rng = np.random.default_rng(3)
    database = unit_rows(rng, 6, 4)
    with pytest.raises(ValueError, match=r"queries \[2, 3\] vs database \[6, 4\]"):
        search(unit_rows(rng, 2, 3), database, **ranked())
    bad = database.copy()
    bad[4, 1] = np.nan
    with pytest.raises(ValueError, match="database descriptors: row 4"):
        search(database, bad, **ranked())
    with pytest.raises(ValueError, match="query descriptors: row 4"):
        search(bad, database, **ranked())
    with pytest.raises(ValueError, match="empty database"):
        search(database, np.zeros((0, 4), dtype=np.float32), **ranked())
    with pytest.raises(ValueError, match="depth must be >= 1"):
        search(database, database, **ranked(depth=0))
    with pytest.raises(ValueError, match="exclude_self"):
        search(database[:3], database, **ranked(), exclude_self=True)
