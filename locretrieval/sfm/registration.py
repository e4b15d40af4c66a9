"""Register queries in maps: a query's pose from its 2D-3D correspondences with a map
(`register_query`), and every query of a run in worker processes, outcomes cached
(`register_queries`)."""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from locretrieval.estimates import LOCALIZED, PoseEstimates
from locretrieval.pool import WORKERS
from locretrieval.retrieval import Ranking
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.pnp import NO_KEYPOINTS, TOO_FEW_MATCHES, estimate_absolute_pose
from locretrieval.sfm.pose_cache import Outcome, PoseCache
from locretrieval.sfm.query_tasks import QueryTask, outcomes_per_image_set, query_tasks
from locretrieval.sfm.sparse_map import SparseMap

log = logging.getLogger(__name__)

#: The ``method`` of the SfM paradigms' pose estimates: PnP + RANSAC on the retrieved images' 3D points.
SFM_METHOD = "pnp"
#: Seconds between saves of the registration outcomes while a paradigm runs.
SAVE_SECONDS = 1.0


def correspondences(
    query_keypoints: np.ndarray,
    query_matches: Mapping[int, np.ndarray],
    sparse_map: SparseMap,
    slots: Mapping[int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """2D-3D correspondences ``(points2D [m, 2], points3D [m, 3])`` of a query through the map
    points its matched database keypoints observe; ``slots`` maps database index -> image
    index in ``sparse_map``. A (query keypoint, 3D point) pair reached twice counts once."""
    pairs = []
    for database_index, matches in query_matches.items():
        ids = sparse_map.observations[slots[database_index]][matches[:, 1]]
        observed = ids >= 0
        pairs.append(np.column_stack([matches[observed, 0], ids[observed]]))
    if not pairs:
        return np.empty((0, 2)), np.empty((0, 3))
    unique = np.unique(np.concatenate(pairs).astype(np.int64), axis=0)
    return query_keypoints[unique[:, 0]].astype(np.float64), sparse_map.points[unique[:, 1]]


def register_query(
    inputs: SfmInputs,
    query: int,
    query_keypoints: np.ndarray,
    query_matches: Mapping[int, np.ndarray],
    sparse_map: SparseMap,
    slots: Mapping[int, int],
) -> Outcome:
    """The query's pose from its correspondences with ``sparse_map``, or the failure reason."""
    if not len(query_keypoints):
        return NO_KEYPOINTS
    points2D, points3D = correspondences(query_keypoints, query_matches, sparse_map, slots)
    if not len(points2D):
        return TOO_FEW_MATCHES
    result = estimate_absolute_pose(points2D, points3D, inputs.scene.queries.cameras[query], inputs.settings.pnp)
    return result if isinstance(result, str) else result[:2]


def _pending_count(task: QueryTask) -> int:
    """A query's units of work in the registration stage's progress: its registrations not cached."""
    return len(task.pending())


def _never(images: tuple[int, ...]) -> Outcome:
    raise AssertionError(f"image set {images} of a complete task has no known outcome")


def register_queries(
    paradigm: str,
    rankings: Sequence[Ranking],
    ks: Sequence[list[int]],
    localize: Callable[[Any, QueryTask], list[list[Outcome]]],
    shared: Any,
    workers: int,
    cache: PoseCache,
    queries: Sequence[int] | None = None,
) -> list[PoseEstimates] | None:
    """Run ``localize(shared, task)`` (outcomes ``[ranking][k]`` of one query) in worker processes
    on every query with an image set whose outcome ``cache`` does not hold, add the new outcomes
    to the cache as they arrive (saved every `SAVE_SECONDS` and at the end, also after an error),
    and gather one `PoseEstimates` per ranking; failures are logged.
    With ``queries`` (a shard's), only those are localised and cached, and nothing is gathered."""
    tasks = query_tasks(rankings, ks, cache, queries)
    pending = [task for task in tasks if not task.complete]
    if len(pending) < len(tasks):
        log.info(
            "%s: %d of %d queries fully read from the registration cache",
            paradigm,
            len(tasks) - len(pending),
            len(tasks),
        )
    computed = iter(WORKERS.map(localize, pending, workers, paradigm, shared, _pending_count))
    outcomes = []
    try:
        for task in tasks:
            outcomes.append(outcomes_per_image_set(task, _never) if task.complete else next(computed))
            for top, ranking_ks, per_k in zip(task.top, task.ks, outcomes[-1]):
                for k, outcome in zip(ranking_ks, per_k):
                    cache.put(task.query, top[:k], outcome)
            cache.save(every=SAVE_SECONDS)  # a killed run loses at most this many seconds of outcomes
    finally:
        cache.save()  # an error or an interrupt keeps what finished
    if queries is not None:
        return None
    return [
        _estimates(paradigm, ranking, ranking_ks, [per_query[r] for per_query in outcomes])
        for r, (ranking, ranking_ks) in enumerate(zip(rankings, ks))
    ]


def _estimates(paradigm: str, ranking: Ranking, ks: list[int], outcomes: Sequence[Sequence[Outcome]]) -> PoseEstimates:
    """One ranking's `PoseEstimates` from its outcomes ``[query][k]``; failures are logged."""
    shape = (len(ks), ranking.num_queries)
    qvec, tvec = np.full((*shape, 4), np.nan), np.full((*shape, 3), np.nan)
    failures = np.full(shape, LOCALIZED, dtype=object)
    for q, per_query in enumerate(outcomes):
        for n, outcome in enumerate(per_query):
            if isinstance(outcome, str):
                failures[n, q] = outcome
            else:
                qvec[n, q], tvec[n, q] = outcome
    reasons = Counter(reason for reason in failures.ravel() if reason != LOCALIZED)
    if reasons:
        log.info(
            "%s / %s: not localised %s (over %d queries x k=%s)",
            paradigm,
            ranking.name,
            dict(reasons),
            ranking.num_queries,
            ks,
        )
    return PoseEstimates(ranking.name, ranking.kind, paradigm, SFM_METHOD, ks, qvec, tvec, failures.astype(str))
