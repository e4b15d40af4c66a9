"""Paradigm 2a, local SfM (paper Sec. 3.2 and 3.9): a map built on the fly from the top-k images.

For each query, ranking and k:

1. the map images are the query's top-k database images (their known poses are kept fixed);
2. map-map matches (``map_matches``, a `MapMatches` chosen by ``_target_``,
   ``configs/paradigms/local_sfm/map_matches/``):
   - `DatabaseMapMatches` (the paper's protocol): every pair of the k images is matched (mutual
     nearest neighbours + ratio test). Database pairs are matched once for all queries,
     rankings and k and cached;
   - `QueryMapMatches`: derived from the query's matches (Sec. 4.1.2, discussion): if query keypoint
     q1 matches m1 in one map image and m2 in another, (m1, m2) is a map-map match; no
     database pair is matched at all;
   either way, map-map matches are then kept by ``sfm.database_verification`` (within
   ``max_epipolar_error`` pixels of the epipolar geometry of the two known poses);
3. COLMAP's triangulator builds tracks across the k images and triangulates them
   (``sfm.triangulation``: COLMAP's, or the batched one, every map of a query in one call); the map is
   cached in ``<cache_dir>/local_maps/`` keyed by its images, the matches' store and the
   triangulation settings (and, with map matches derived from the query's, the query), so a map shared by
   several queries or a rerun is triangulated once;
4. the query's matches to the k images (verified per ``matching.query_verification``) give
   2D-3D correspondences through the triangulated keypoints, and LO-RANSAC P3P with
   non-linear refinement (``pnp`` options) estimates its pose; outcomes are cached in
   ``<cache_dir>/poses/`` by query and image set (`PoseCache`), keyed by what the maps are
   keyed by, the query matches' store and the PnP settings.

A query is not localised (with its reason) when its ranking is empty, k < 2 images are
available ("too few images"), the map has no point, or PnP fails.
"""

from __future__ import annotations

import abc
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from math import comb
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from locretrieval.cache import config_key
from locretrieval.config import part
from locretrieval.paradigms.sfm import Localize, SfmParadigm
from locretrieval.pool import WORKERS
from locretrieval.retrieval import EMPTY, Ranking
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.pnp import EMPTY_RETRIEVAL, NO_3D_POINTS, TOO_FEW_IMAGES
from locretrieval.sfm.pose_cache import Outcome, PoseCache
from locretrieval.sfm.query_tasks import QueryTask, outcomes_per_image_set, query_tasks
from locretrieval.sfm.registration import register_query
from locretrieval.sfm.sparse_map import SparseMap
from locretrieval.sfm.triangulation import MapInput
from locretrieval.sfm.verification import VerificationBatch
from locretrieval.sfm.work import Work, database_pair_work

#: Bump when the meaning of cached local maps changes.
CACHE_VERSION = 1

#: Database pairs ``(a, b)``, a < b, by index.
IndexPairs = list[tuple[int, int]]


@dataclass
class QueryMaps:
    """What one query's local maps are built from: the cached ``inputs``, the ``query``'s index, its
    ``keypoints``, its ``matches`` to each map image (by database index) and the map images'
    ``database_keypoints`` (by name)."""

    inputs: SfmInputs
    query: int
    keypoints: np.ndarray
    matches: Mapping[int, np.ndarray]
    database_keypoints: Mapping[str, np.ndarray]


class MapMatches(abc.ABC):
    """Where the matches between the images of a local map come from. A new source subclasses
    this, in any package, and is chosen by its ``_target_`` (``paradigms.local_sfm.map_matches``)."""

    @abc.abstractmethod
    def identity(self) -> str:
        """What determines the matches, beside `source` (part of the maps' and outcomes' cache keys)."""

    def database_pairs(
        self, rankings: Sequence[Ranking], ks: Sequence[Sequence[int]], queries: Sequence[int] | None
    ) -> np.ndarray:
        """The database pairs ``[P, 2]`` to match before the maps of ``queries`` (None: all) are
        built (default: none)."""
        return np.empty((0, 2), dtype=np.int64)

    def pair_bound(self, pairs_per_query: int, queries: int, num_rankings: int, database: int) -> int:
        """At most how many database pairs `database_pairs` gives for ``num_rankings`` rankings not
        computed yet (``pairs_per_query``: the pairs among one query's deepest k images)."""
        return 0

    @abc.abstractmethod
    def source(self, inputs: SfmInputs, query: int) -> list[str]:
        """What the matches of ``query``'s maps are read from (part of a map's cache key)."""

    @abc.abstractmethod
    def matches(self, pairs: IndexPairs, query: QueryMaps) -> dict[tuple[int, int], np.ndarray]:
        """Pose-verified matches ``[m, 2]`` of every database pair of ``pairs`` of one query's maps."""


@dataclass
class DatabaseMapMatches(MapMatches):
    """The paper's protocol: every pair of the k images matched (and verified against their poses),
    once for all queries, rankings and k, cached."""

    def identity(self) -> str:
        return "database"

    def database_pairs(
        self, rankings: Sequence[Ranking], ks: Sequence[Sequence[int]], queries: Sequence[int] | None
    ) -> np.ndarray:
        return local_map_pairs(rankings, ks, queries)

    def pair_bound(self, pairs_per_query: int, queries: int, num_rankings: int, database: int) -> int:
        return min(num_rankings * queries * pairs_per_query, comb(database, 2))

    def source(self, inputs: SfmInputs, query: int) -> list[str]:
        return [_database_matches(inputs)]

    def matches(self, pairs: IndexPairs, query: QueryMaps) -> dict[tuple[int, int], np.ndarray]:
        inputs, names = query.inputs, query.inputs.scene.database.names
        loaded = inputs.database_pairs.load([(names[a], names[b]) for a, b in pairs], inputs.database_verification)
        return {(a, b): loaded[(names[a], names[b])] for a, b in pairs}


@dataclass
class QueryMapMatches(MapMatches):
    """Derived from the query's matches (paper Sec. 4.1.2, discussion): if query keypoint q1 matches
    m1 in one map image and m2 in another, (m1, m2) is a map-map match, kept by the database
    verification (``sfm.database_verification``: within ``max_epipolar_error`` pixels of the two
    known poses' epipolar geometry); no database pair is matched."""

    def identity(self) -> str:
        return "query"

    def source(self, inputs: SfmInputs, query: int) -> list[str]:
        return [inputs.query_pairs.store(inputs.query_verification).folder.name, inputs.scene.queries.names[query]]

    def matches(self, pairs: IndexPairs, query: QueryMaps) -> dict[tuple[int, int], np.ndarray]:
        partner = {}
        for image, matches in query.matches.items():
            partner[image] = np.full(len(query.keypoints), -1, dtype=np.int64)
            partner[image][matches[:, 0]] = matches[:, 1]
        derived = []
        for a, b in pairs:
            both = (partner[a] >= 0) & (partner[b] >= 0)
            derived.append(np.column_stack([partner[a][both], partner[b][both]]).astype(np.int32))
        database, keypoints = query.inputs.scene.database, query.database_keypoints
        batch = VerificationBatch(database, database, pairs, derived, keypoints, keypoints)
        return dict(zip(pairs, query.inputs.database_verification.verify(batch)))


#: What every task of a query's local maps reads: the cached inputs, the map matches, the maps' folder.
LocalMaps = tuple[SfmInputs, MapMatches, Path]


@dataclass
class LocalSfm(SfmParadigm):
    """Paradigm 2a (``configs/paradigms/local_sfm.yaml``). ``map_matches``: where the matches among
    a local map's images come from (a `MapMatches`, chosen by its ``_target_``:
    ``paradigms/local_sfm/map_matches=database|query``). What it needs: no shared map, each query's
    maps triangulated (in worker processes) before it is registered in them."""

    map_matches: Any = part(MapMatches, "paradigms/local_sfm/map_matches")
    label: ClassVar[str] = "local_sfm"

    def query_map_pairs(
        self,
        inputs: SfmInputs,
        rankings: Sequence[Ranking],
        ks: Sequence[Sequence[int]],
        queries: Sequence[int] | None,
    ) -> list[tuple[str, str]]:
        """The database pairs (names) every local map of ``queries`` (None: all) needs matched first
        (`MapMatches.database_pairs`)."""
        names = inputs.scene.database.names
        return [(names[a], names[b]) for a, b in self.map_matches.database_pairs(rankings, ks, queries)]

    def triangulate_query_maps(
        self, inputs: SfmInputs, rankings: Sequence[Ranking], ks: Sequence[list[int]], queries: Sequence[int]
    ) -> None:
        """The local maps of each query of ``queries`` whose registration is not cached and whose
        map is not either, triangulated and cached (`triangulate_query`, in worker processes)."""
        shared = self.local_maps(inputs)
        tasks, owned, counted = [], {}, set()
        for task in query_tasks(rankings, ks, self.pose_cache(inputs), queries):
            new = {path for path in _map_paths(shared, task).values() if not path.is_file()}
            if new:  # its progress counts the maps no earlier task of the call builds (queries share maps)
                tasks.append(task)
                owned[task.query], counted = len(new - counted), counted | new
        for _ in WORKERS.map(
            triangulate_query,
            tasks,
            inputs.settings.processes,
            f"{self.label}: triangulate",
            shared,
            units=lambda task: owned[task.query],
        ):
            pass

    def local_maps(self, inputs: SfmInputs) -> LocalMaps:
        """What every task of a query's local maps reads (`LocalMaps`)."""
        return inputs, self.map_matches, inputs.cache_dir / "local_maps"

    def pose_cache(self, inputs: SfmInputs) -> PoseCache:
        """The registration outcomes, keyed by what the local maps are keyed by."""
        maps = [
            CACHE_VERSION,
            self.map_matches.identity(),
            _database_matches(inputs),
            inputs.settings.triangulation.identity(),
        ]
        return inputs.pose_cache("local_sfm", maps, inputs.cache_dir)

    def registration(self, inputs: SfmInputs) -> tuple[Localize, LocalMaps]:
        """Each query registered in its local maps (`register_query_in_maps`)."""
        return register_query_in_maps, self.local_maps(inputs)

    def count_maps(
        self,
        inputs: SfmInputs,
        rankings: Sequence[Ranking] | None,
        tasks: Sequence[QueryTask] | None,
        num_rankings: int,
    ) -> tuple[Work, Work, float]:
        """The database pairs of every local map (`MapMatches.database_pairs`, bounded by
        `MapMatches.pair_bound`) and its maps of 2 images or more, distinct by their cache keys."""
        k, scene = self.k, inputs.scene
        pairs_per_map = float(np.mean([comb(min(size, len(scene.database)), 2) for size in k if size >= 2] or [0]))
        if rankings is None:
            queries, depth = len(scene.queries), min(max(k), len(scene.database))
            bound = self.map_matches.pair_bound(comb(depth, 2), queries, num_rankings, len(scene.database))
            maps = num_rankings * queries * sum(1 for size in k if size >= 2)
            return Work(bound, bound), Work(maps, maps), pairs_per_map
        ks = [ranking.clamp_ks(k) for ranking in rankings]
        database_pairs = database_pair_work(inputs, self.query_map_pairs(inputs, rankings, ks, None))
        maps = {
            _map_key(inputs, self.map_matches, task.query, images)
            for task in tasks
            for images in task.image_sets()
            if len(images) >= 2
        }
        new_maps = {key for key in maps if not (inputs.cache_dir / "local_maps" / f"{key}.npz").is_file()}
        return database_pairs, Work(len(maps), len(new_maps)), pairs_per_map


def _database_matches(inputs: SfmInputs) -> str:
    """The name of the pose-verified database matches' store (features, ratio, epipolar bound, poses)."""
    return inputs.database_pairs.store(inputs.database_verification).folder.name


def local_map_pairs(
    rankings: Sequence[Ranking], ks: Sequence[Sequence[int]], queries: Sequence[int] | None = None
) -> np.ndarray:
    """Distinct database pairs ``[P, 2]`` (a < b) of any local map: both among one query's top
    ``max(k)`` (of ``queries``, or every query)."""
    pairs = [np.empty((0, 2), dtype=np.int64)]
    rows = slice(None) if queries is None else np.asarray(queries, dtype=np.int64)
    for ranking, ranking_ks in zip(rankings, ks):
        top = ranking.indices[rows, : max(ranking_ks)]
        first, second = np.triu_indices(top.shape[1], 1)
        a, b = top[:, first].ravel(), top[:, second].ravel()
        valid = (a != EMPTY) & (b != EMPTY) & (a != b)
        pairs.append(np.column_stack([np.minimum(a, b), np.maximum(a, b)])[valid])
    return np.unique(np.concatenate(pairs), axis=0)


def _map_paths(shared: LocalMaps, task: QueryTask) -> dict[tuple[int, ...], Path]:
    """Where the query's maps (its image sets whose outcome is not known, of 2 images or more) are cached."""
    inputs, map_matches, maps = shared
    return {
        selected: maps / f"{_map_key(inputs, map_matches, task.query, selected)}.npz"
        for selected in sorted(task.pending())
        if len(selected) >= 2
    }


def _new_maps(shared: LocalMaps, task: QueryTask) -> list[tuple[int, ...]]:
    """The query's maps not cached yet."""
    return [selected for selected, path in _map_paths(shared, task).items() if not path.is_file()]


def triangulate_query(shared: LocalMaps, task: QueryTask) -> int:
    """The query's maps not cached yet (`_new_maps`), triangulated in one call of the
    triangulation from their pose-verified map matches and cached; returns how many."""
    inputs, map_matches, _ = shared
    database = inputs.scene.database
    paths, built = _map_paths(shared, task), _new_maps(shared, task)
    images = sorted({i for selected in built for i in selected})
    query_keypoints, query_matches = inputs.query_matches(task.query, images)
    keypoints = inputs.database_features.keypoints([database.names[i] for i in images])
    pairs = sorted({(a, b) for selected in built for a in selected for b in selected if a < b})
    map_pairs = map_matches.matches(pairs, QueryMaps(inputs, task.query, query_keypoints, query_matches, keypoints))
    sparse_maps = inputs.settings.triangulation.triangulate_many(
        [
            MapInput(
                [database.cameras[i] for i in selected],
                database.qvec[list(selected)],
                database.tvec[list(selected)],
                [keypoints[database.names[i]] for i in selected],
                {(s, t): map_pairs[(a, b)] for s, a in enumerate(selected) for t, b in enumerate(selected) if a < b},
            )
            for selected in built
        ]
    )
    for selected, sparse_map in zip(built, sparse_maps):
        sparse_map.save(paths[selected])
    return len(built)


def register_query_in_maps(shared: LocalMaps, task: QueryTask) -> list[list[Outcome]]:
    """Outcomes ``[ranking][k]`` of one query, registered once in each of its maps (the image sets
    whose outcome is not known, read from the cache: `triangulate_query` built any missing, here
    too when another job's share left one out), whichever rankings, ks and orders select its images."""
    inputs = shared[0]
    if _new_maps(shared, task):
        triangulate_query(shared, task)
    paths = _map_paths(shared, task)
    images = sorted({i for selected in task.pending() for i in selected})
    query_keypoints, query_matches = inputs.query_matches(task.query, images)

    def localize(selected: tuple[int, ...]) -> Outcome:
        if not selected:
            return EMPTY_RETRIEVAL
        if len(selected) < 2:
            return TOO_FEW_IMAGES
        sparse_map = SparseMap.load(paths[selected])
        if not sparse_map.num_points:
            return NO_3D_POINTS
        slots = {i: s for s, i in enumerate(selected)}
        return register_query(
            inputs, task.query, query_keypoints, {i: query_matches[i] for i in selected}, sparse_map, slots
        )

    return outcomes_per_image_set(task, localize)


def _map_key(inputs: SfmInputs, map_matches: MapMatches, query: int, selected: tuple[int, ...]) -> str:
    """Cache key of a local map: its images, where its matches come from (`MapMatches.source`:
    the database matches' store, or the query's matches and the query) and the triangulation settings."""
    names = [inputs.scene.database.names[i] for i in selected]
    source = map_matches.source(inputs, query)
    return config_key(CACHE_VERSION, map_matches.identity(), source, names, inputs.settings.triangulation.identity())
