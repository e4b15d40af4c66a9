"""What the SfM paradigms (2a local, 2b global) share: settings, feature and match caches,
the union of query-database pairs over all rankings, per-query workers, and the results.

Every ranking is handled in the same run so that features and matches are shared: the query
pairs are the union over rankings of each query with its top ``max(k)`` database images, each
matched once; the per-query work then reads only cached inputs.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from locretrieval.cache import config_key
from locretrieval.config import part, require
from locretrieval.estimates import LOCALIZED, PoseEstimates
from locretrieval.pool import WORKERS, resolve_workers
from locretrieval.retrieval import EMPTY, Ranking
from locretrieval.scene import Scene
from locretrieval.sfm.features import FeatureStore, LocalFeatures, extract_features, feature_store
from locretrieval.sfm.matching import MatchingSettings, PairMatcher
from locretrieval.sfm.pairs import PairSelection
from locretrieval.sfm.pnp import NO_KEYPOINTS, TOO_FEW_MATCHES, PnPSettings, estimate_absolute_pose
from locretrieval.sfm.pose_cache import Outcome, PoseCache
from locretrieval.sfm.sparse_map import SparseMap
from locretrieval.sfm.triangulation import Triangulation
from locretrieval.sfm.verification import PairVerification

log = logging.getLogger(__name__)


#: The ``method`` of the SfM paradigms' pose estimates: PnP + RANSAC on the retrieved images' 3D points.
SFM_METHOD = "pnp"
#: Seconds between saves of the registration outcomes while a paradigm runs.
SAVE_SECONDS = 1.0


@dataclass
class SfmSettings:
    """The ``sfm`` config group, shared by local SfM (2a), global SfM (2b) and the
    co-observation ground truth so that they share their cached features and matches:
    local ``features`` (a `LocalFeatures` chosen by ``_target_``), ``matching``, the
    ``query_verification`` of query-database matches and the ``database_verification`` of
    database pairs (each a `PairVerification` chosen by ``_target_``), ``triangulation`` with
    known poses (a `Triangulation` chosen by ``_target_``), ``pnp``
    registration, the database pairs of global maps (``map_pairs``, by frustum overlap) and the
    worker processes (``workers``: ``null`` or 0, one per core; 1, in this process). Which share
    of the work a job does is the job's (`locretrieval.shard.Shard`), not a setting of this group."""

    features: Any = part(LocalFeatures, "sfm/features")
    matching: MatchingSettings
    query_verification: Any = part(PairVerification, "sfm/query_verification")
    database_verification: Any = part(PairVerification, "sfm/database_verification")
    triangulation: Any = part(Triangulation, "sfm/triangulation")
    pnp: PnPSettings
    map_pairs: PairSelection
    workers: int | None

    def __post_init__(self) -> None:
        require(self.workers is None or self.workers >= 0, "workers", f"must be >= 0 or null, got {self.workers}")

    @property
    def processes(self) -> int:
        """Worker processes to use (`resolve_workers`)."""
        return resolve_workers(self.workers)


@dataclass
class SfmInputs:
    """Cached features and matches of a scene (in ``cache_dir``), picklable for worker processes."""

    scene: Scene
    settings: SfmSettings
    cache_dir: Path
    database_features: FeatureStore
    query_features: FeatureStore
    database_pairs: PairMatcher
    query_pairs: PairMatcher

    @classmethod
    def prepare(cls, scene: Scene, settings: SfmSettings, cache_dir: Path, extract: bool = True) -> "SfmInputs":
        """Extract (or reuse) the local features of both image sets (``extract=False``: only
        name their caches, as far as they are filled, to plan the work)."""
        if extract:
            database_features, query_features = (
                extract_features(images, settings.features, cache_dir, settings.processes)
                for images in (scene.database, scene.queries)
            )
        else:
            database_features, query_features = (
                feature_store(images, settings.features, cache_dir) for images in (scene.database, scene.queries)
            )
        return cls(
            scene,
            settings,
            Path(cache_dir),
            database_features,
            query_features,
            PairMatcher(
                scene.database, database_features, scene.database, database_features, settings.matching, cache_dir
            ),
            PairMatcher(scene.queries, query_features, scene.database, database_features, settings.matching, cache_dir),
        )

    @property
    def map_pairs(self) -> PairSelection:
        """The database pairs of global maps, ``far`` defaulting to the scene's frustum far plane."""
        return self.settings.map_pairs.for_scene(self.scene)

    @property
    def query_verification(self) -> PairVerification:
        return self.settings.query_verification

    @property
    def database_verification(self) -> PairVerification:
        return self.settings.database_verification

    def ranked_pairs(
        self, rankings: Sequence[Ranking], ks: Sequence[Sequence[int]], queries: Sequence[int] | None = None
    ) -> set[tuple[str, str]]:
        """Every (query, database image) name pair of a query's top ``max(k)`` of a ranking (of
        the ``queries`` given, or all)."""
        query_names, database = self.scene.queries.names, self.scene.database.names
        rows = np.arange(len(query_names)) if queries is None else np.asarray(queries, dtype=np.int64)
        pairs = set()
        for ranking, ranking_ks in zip(rankings, ks):
            top = ranking.indices[rows, : max(ranking_ks)]
            row, slot = np.nonzero(top != EMPTY)
            pairs.update((query_names[q], database[i]) for q, i in zip(rows[row], top[row, slot]))
        return pairs

    def pose_cache(self, paradigm: str, maps: Any, cache_dir: Path) -> PoseCache:
        """The cached registration outcomes of ``paradigm`` (`PoseCache`) in ``<cache_dir>/poses/``,
        keyed by ``maps`` (what the paradigm's maps are keyed by), the query matches' store
        (features of both sets, ratio, verification) and the PnP settings."""
        queries = self.query_pairs.store(self.query_verification).folder.name
        key = config_key(maps, queries, dataclasses.asdict(self.settings.pnp))
        return PoseCache(cache_dir / "poses" / f"{paradigm}-{key}", self.scene.queries.names, self.scene.database.names)

    def query_matches(self, query: int, database: Sequence[int]) -> tuple[np.ndarray, dict[int, np.ndarray]]:
        """The query's keypoints and its (verified) matches to each database image."""
        name = self.scene.queries.names[query]
        keypoints = self.query_features.keypoints([name])[name]
        names = [self.scene.database.names[i] for i in database]
        matches = self.query_pairs.load([(name, other) for other in names], self.query_verification)
        return keypoints, {i: matches[(name, other)] for i, other in zip(database, names)}


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


@dataclass(frozen=True)
class QueryTask:
    """One query's top database images per ranking (``EMPTY`` removed), the ks of each, and
    the outcomes already known (cached) of some of its image sets (sorted index tuples)."""

    query: int
    top: tuple[tuple[int, ...], ...]
    ks: tuple[tuple[int, ...], ...]
    known: dict[tuple[int, ...], Outcome] = field(default_factory=dict, compare=False)

    def image_sets(self) -> set[tuple[int, ...]]:
        """Every distinct top-k image set (sorted) of every ranking and k."""
        return {tuple(sorted(top[:k])) for top, ks in zip(self.top, self.ks) for k in ks}

    def pending(self) -> set[tuple[int, ...]]:
        """The image sets whose outcome is not known."""
        return self.image_sets() - self.known.keys()

    @property
    def complete(self) -> bool:
        return not self.pending()


def outcomes_per_image_set(task: QueryTask, localize: Callable[[tuple[int, ...]], Outcome]) -> list[list[Outcome]]:
    """Outcomes ``[ranking][k]`` of one query, where ``localize(images)`` gives the outcome of
    the top-k database images as a sorted tuple; it runs once per distinct image set that is not
    known already, however many rankings and ks (or orders within a ranking) select it."""
    localize = functools.cache(localize)

    def outcome(images: tuple[int, ...]) -> Outcome:
        return task.known[images] if images in task.known else localize(images)

    return [[outcome(tuple(sorted(top[:k]))) for k in ks] for top, ks in zip(task.top, task.ks)]


def query_tasks(
    rankings: Sequence[Ranking], ks: Sequence[Sequence[int]], cache: PoseCache, queries: Sequence[int] | None = None
) -> list[QueryTask]:
    """Per query (of ``queries``, or every one), its top ``max(k)`` database images of each
    ranking and its cached outcomes."""
    rows = [ranking.indices[:, : max(ranking_ks)] for ranking, ranking_ks in zip(rankings, ks)]
    tasks = []
    for q in range(rankings[0].num_queries) if queries is None else queries:
        task = QueryTask(q, tuple(tuple(int(i) for i in row[q] if i != EMPTY) for row in rows), tuple(map(tuple, ks)))
        for images in task.image_sets():
            outcome = cache.get(q, images)
            if outcome is not None:
                task.known[images] = outcome
        tasks.append(task)
    return tasks


def _pending_count(task: QueryTask) -> int:
    """A query's units of work in the registration stage's progress: its registrations not cached."""
    return len(task.pending())


def _never(images: tuple[int, ...]) -> Outcome:
    raise AssertionError(f"image set {images} of a complete task has no known outcome")


def run_queries(
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
