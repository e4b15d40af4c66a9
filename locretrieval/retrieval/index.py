"""Exact inner-product search with faiss: descriptors -> `Ranking`."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import faiss
import numpy as np

from locretrieval.config import require
from locretrieval.retrieval.ranking import Ranking
from locretrieval.threads import map_single_threaded

log = logging.getLogger(__name__)


@dataclass
class RetrievalSettings:
    """The ``retrieval`` config section: ``depth`` images kept per query in every ranking (K,
    the paper: 50) and ``chunk_size`` queries searched at once."""

    depth: int
    chunk_size: int

    def __post_init__(self) -> None:
        require(self.depth >= 1, "depth", f"must be >= 1, got {self.depth}")
        require(self.chunk_size >= 1, "chunk_size", f"must be >= 1, got {self.chunk_size}")


def _as_descriptor_matrix(values: np.ndarray, label: str) -> np.ndarray:
    """``values`` as a C-contiguous ``float32 [rows, D]`` matrix; a named error unless 2-D and finite."""
    matrix = np.ascontiguousarray(values, dtype=np.float32)
    if matrix.ndim != 2:
        raise ValueError(f"{label} descriptors must be a [rows, D] matrix, got shape {matrix.shape}")
    finite = np.isfinite(matrix).all(axis=1)
    if not finite.all():
        raise ValueError(f"{label} descriptors: row {int(np.argmin(finite))} holds non-finite values")
    return matrix


def _drop_self(indices: np.ndarray, scores: np.ndarray, rows: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray]:
    """Remove each row's own index from ``depth + 1`` results (the last one where it is absent)."""
    is_self = indices == rows[:, None]
    is_self[~is_self.any(axis=1), -1] = True
    keep = np.argsort(is_self, axis=1, kind="stable")[:, :depth]
    return np.take_along_axis(indices, keep, axis=1), np.take_along_axis(scores, keep, axis=1)


def search(
    query_descriptors: np.ndarray,
    database_descriptors: np.ndarray,
    depth: int,
    name: str,
    chunk_size: int,
    exclude_self: bool = False,
) -> Ranking:
    """Top-``depth`` database images per query by inner product (cosine for L2-normalised rows).

    An exact faiss ``IndexFlatIP`` is searched ``chunk_size`` queries at a time (each chunk on
    one thread, chunks in parallel), so no ``[Q, N]`` matrix is ever formed and the scores do not
    depend on the machine's thread count. Rows are ordered by decreasing score, ties by
    increasing database index (which of several candidates tied at the last slot is kept
    is faiss's choice). ``exclude_self`` ranks a set against itself (the same
    array): row ``i`` never contains ``i`` and still holds ``depth`` results. A ``depth``
    beyond the available images is clamped with a warning. The ranking keeps the
    descriptors (``kind="descriptor"``), which BDI/CSI weighting reads.
    """
    queries = _as_descriptor_matrix(query_descriptors, "query")
    database = _as_descriptor_matrix(database_descriptors, "database")
    if queries.shape[1] != database.shape[1]:
        raise ValueError(
            f"descriptor dimension mismatch: queries {list(queries.shape)} vs database {list(database.shape)}"
        )
    if len(database) == 0:
        raise ValueError("cannot search an empty database")
    if depth < 1:
        raise ValueError(f"depth must be >= 1, got {depth}")
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
    if exclude_self and not np.array_equal(queries, database):
        raise ValueError(
            f"exclude_self ranks a set against itself, but queries {list(queries.shape)} and "
            f"database {list(database.shape)} differ"
        )
    available = len(database) - int(exclude_self)
    if available < 1:
        raise ValueError("ranking a single image against itself with exclude_self leaves no candidate")
    if depth > available:
        log.warning(
            "ranking %r: depth %d exceeds the %d candidate images; clamped to %d", name, depth, available, available
        )
        depth = available

    index = faiss.IndexFlatIP(database.shape[1])
    index.add(database)
    indices = np.empty((len(queries), depth), dtype=np.int64)
    scores = np.empty((len(queries), depth), dtype=np.float32)

    def search_chunk(start: int) -> None:
        stop = min(start + chunk_size, len(queries))
        chunk_scores, chunk_indices = index.search(queries[start:stop], depth + int(exclude_self))
        if exclude_self:
            chunk_indices, chunk_scores = _drop_self(chunk_indices, chunk_scores, np.arange(start, stop), depth)
        order = np.lexsort((chunk_indices, -chunk_scores), axis=1)
        indices[start:stop] = np.take_along_axis(chunk_indices, order, axis=1)
        scores[start:stop] = np.take_along_axis(chunk_scores, order, axis=1)

    # each chunk's product on one thread, chunks in parallel: the same scores (so the same order) on any machine
    map_single_threaded(search_chunk, range(0, len(queries), chunk_size))
    return Ranking(name, indices, scores, "descriptor", queries, database)
