"""`Ranking`: for every query, an ordered list of database images.

Descriptor searches and ground-truth definitions both produce a `Ranking`, and every
paradigm consumes one; that symmetry is what makes ground truth an upper bound.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import sparse

#: Index value of an empty slot (fewer than K candidates for that query).
EMPTY = -1


@dataclass(frozen=True)
class Ranking:
    """Top-K database images per query.

    ``indices [Q, K]`` are database indices, best first, ``EMPTY`` (-1) for unfilled slots
    (always at the end of a row). ``scores [Q, K]`` are similarities, higher is better (a
    ground truth whose natural score is a distance stores its negation). ``kind`` says
    whether a descriptor, a ground-truth definition (an upper bound) or a baseline (e.g.
    random, a lower bound) produced it. Descriptor rankings keep
    the L2-normalised descriptors ``query_descriptors [Q, D]`` and ``database_descriptors
    [N, D]``, which BDI weighting needs; their scores are the cosine similarities
    ``d_q . d_i`` (as `search` returns them), which CSI weighting uses.
    """

    name: str
    indices: np.ndarray
    scores: np.ndarray
    kind: Literal["descriptor", "groundtruth", "baseline"]
    query_descriptors: np.ndarray | None = None
    database_descriptors: np.ndarray | None = None

    def __post_init__(self) -> None:
        indices = np.asarray(self.indices, dtype=np.int64)
        scores = np.asarray(self.scores, dtype=np.float32)
        if indices.ndim != 2 or indices.shape != scores.shape:
            raise ValueError(
                f"ranking {self.name!r}: indices {indices.shape} and scores {scores.shape} must both be [Q, K]"
            )
        filled = indices != EMPTY
        if (filled[:, 1:] & ~filled[:, :-1]).any():
            raise ValueError(f"ranking {self.name!r}: empty slots must come after filled ones")
        if self.kind not in ("descriptor", "groundtruth", "baseline"):
            raise ValueError(f"ranking {self.name!r}: unknown kind {self.kind!r}")
        if self.query_descriptors is not None:
            if self.database_descriptors is None or len(self.query_descriptors) != len(indices):
                raise ValueError(f"ranking {self.name!r}: descriptors do not match the ranking's queries")
        object.__setattr__(self, "indices", indices)
        object.__setattr__(self, "scores", scores)

    @property
    def num_queries(self) -> int:
        return self.indices.shape[0]

    @property
    def depth(self) -> int:
        """K, the number of slots per query."""
        return self.indices.shape[1]

    @property
    def lengths(self) -> np.ndarray:
        """Number of filled slots per query ``[Q]``."""
        return (self.indices != EMPTY).sum(axis=1)

    @property
    def has_descriptors(self) -> bool:
        return self.query_descriptors is not None

    def top(self, k: int) -> "Ranking":
        """The first ``k`` slots (the whole ranking when it is shorter)."""
        return Ranking(
            self.name,
            self.indices[:, :k],
            self.scores[:, :k],
            self.kind,
            self.query_descriptors,
            self.database_descriptors,
        )

    def of_queries(self, rows: np.ndarray) -> "Ranking":
        """The ranking of the queries ``rows`` (indices), in that order."""
        return Ranking(
            self.name,
            self.indices[rows],
            self.scores[rows],
            self.kind,
            None if self.query_descriptors is None else self.query_descriptors[rows],
            self.database_descriptors,
        )

    def clamp_ks(self, ks: list[int]) -> list[int]:
        """The distinct ``ks`` limited to the ranking depth, sorted: the ks a paradigm computes
        (`locretrieval.benchmark` warns once and labels results by the requested k)."""
        if any(int(k) < 1 for k in ks):
            raise ValueError(f"k must be >= 1, got {list(ks)}")
        return sorted({min(int(k), self.depth) for k in ks})


def relevant_hits(indices: np.ndarray, relevance: sparse.csr_matrix) -> np.ndarray:
    """Boolean ``[Q, K]``: the database image in each slot is relevant (``EMPTY`` is not)."""
    indices = np.asarray(indices)
    filled = indices != EMPTY
    rows = np.broadcast_to(np.arange(len(indices))[:, None], indices.shape)
    hits = np.zeros(indices.shape, dtype=bool)
    hits[filled] = np.asarray(relevance[rows[filled], indices[filled]]).ravel()
    return hits


def top_k(scores: np.ndarray, depth: int, valid: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Best ``depth`` entries of each row of a ``[Q, N]`` similarity block (higher is better).

    Entries where ``valid`` is false (or scores that are not finite) are never ranked and
    leave ``EMPTY`` slots; ties keep the lower database index first, so the result is
    deterministic. Call it on chunks of queries to keep memory bounded.
    Returns ``(indices int64[Q, depth'], scores float32[Q, depth'])``, ``depth' = min(depth, N)``.
    """
    scores = np.asarray(scores, dtype=np.float64)
    if valid is not None:
        scores = np.where(valid, scores, -np.inf)
    scores = np.where(np.isfinite(scores), scores, -np.inf)
    depth = min(depth, scores.shape[1])
    order = _best_columns(scores, depth)
    top_scores = np.take_along_axis(scores, order, axis=1)
    filled = np.isfinite(top_scores)
    return np.where(filled, order, EMPTY), np.where(filled, top_scores, 0.0).astype(np.float32)


def _best_columns(scores: np.ndarray, depth: int) -> np.ndarray:
    """Columns of the ``depth`` highest scores of each row, best first, ties by lower column:
    a partial selection, then the stable full sort for the rows where the selection split a
    tie at its boundary (the order of ``-inf`` slots, never ranked, does not matter). Rows
    shorter than ``4 * depth`` are sorted whole: there, selecting first saves little."""
    if not 0 < 4 * depth < scores.shape[1]:
        return np.argsort(-scores, axis=1, kind="stable")[:, :depth]
    chosen = np.argpartition(-scores, depth - 1, axis=1)[:, :depth]
    values = np.take_along_axis(scores, chosen, axis=1)
    chosen = np.take_along_axis(chosen, np.lexsort((chosen, -values), axis=1), axis=1)
    last = np.take_along_axis(scores, chosen[:, -1:], axis=1)
    split = np.isfinite(last[:, 0]) & ((scores == last).sum(axis=1) > (values == last).sum(axis=1))
    chosen[split] = np.argsort(-scores[split], axis=1, kind="stable")[:, :depth]
    return chosen


def ranking_from_scores(
    name: str,
    scores: np.ndarray,
    depth: int,
    kind: Literal["descriptor", "groundtruth", "baseline"],
    valid: np.ndarray | None = None,
) -> Ranking:
    """`Ranking` of a dense ``[Q, N]`` similarity matrix; see `top_k`."""
    indices, top_scores = top_k(scores, depth, valid)
    return Ranking(name, indices, top_scores, kind)


def random_ranking(num_queries: int, num_database: int, depth: int, seed: int) -> Ranking:
    """A seeded uniformly random ranking without repeats: the lower bound of every paradigm."""
    depth = min(depth, num_database)
    rng = np.random.default_rng(seed)
    rows_per_chunk = max(1, (1 << 24) // num_database)
    chunks = [np.empty((0, depth), dtype=np.int64)]
    for start in range(0, num_queries, rows_per_chunk):
        keys = rng.random((min(rows_per_chunk, num_queries - start), num_database))
        chunks.append(top_k(-keys, depth)[0])  # the `depth` smallest keys, in increasing order
    indices = np.concatenate(chunks)
    return Ranking("random", indices, np.zeros(indices.shape, dtype=np.float32), "baseline")
