"""Co-observation ground truth (paper Sec. 3.6.3, "Shared 3D observations").

A joint map of the database and the queries is triangulated with their known poses: the
image pairs are chosen by frustum overlap (database pairs as for the global SfM map, and
each query with its most overlapping database images), matched, verified against the
epipolar geometry of the known poses and triangulated together with COLMAP's triangulator
(`locretrieval.sfm`). The score of (q, t) is the number of 3D points observed by
both; pairs sharing none are not ranked, and a pair is relevant when it shares at least
``min_shared`` points (the paper: one).

Features, matches and the database part of the pair selection are those of the SfM
paradigms (the same caches when the settings agree). A scene read from a reconstruction
(``data=colmap``, ``data=photos``) brings its own tracks (`Scene.observations`): the shared points
are counted from them, with no SfM of ours (as the paper's Aachen and InLoc ground truth comes
from their reference models).
"""

from __future__ import annotations

import dataclasses
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from scipy import sparse

from locretrieval.config import require
from locretrieval.groundtruth.base import DefinitionContext, GradedRows, GroundTruth, groundtruth_from_scores
from locretrieval.paradigms.global_sfm import global_map
from locretrieval.scene import ImageSet, Scene
from locretrieval.sfm.features import extract_features
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.matching import PairMatcher
from locretrieval.sfm.pairs import database_pairs, overlapping_pairs
from locretrieval.sfm.settings import SfmSettings
from locretrieval.sfm.sparse_map import SparseMap


@dataclass
class CoObservationDefinition:
    """Relevant when sharing at least ``min_shared`` 3D points (the paper: 1); in the benchmark,
    each query is matched to its ``query_pairs`` most overlapping database images (by frustum)."""

    min_shared: int
    query_pairs: int
    uses_sfm: ClassVar[bool] = True

    def __post_init__(self) -> None:
        require(self.min_shared >= 1, "min_shared", f"must be >= 1 shared 3D point, got {self.min_shared}")
        require(self.query_pairs >= 1, "query_pairs", f"must be >= 1 database image per query, got {self.query_pairs}")

    def groundtruth(
        self, database: ImageSet, queries: ImageSet, depth: int, name: str, context: DefinitionContext
    ) -> GroundTruth:
        """Database images ranked by the number of 3D points they share with each query.

        ``context.sfm``: the SfM paradigms' settings; its ``map_pairs`` (whose ``far`` must be set)
        select the database pairs, and each query is paired with its ``query_pairs`` most
        overlapping database images with the same frusta. Features and matches are cached under
        ``context.cache_dir`` (a temporary folder when None). With ``context.observations`` (a
        reconstruction's tracks), the points they share are counted instead."""
        if context.observations is not None:
            counts = context.observations.shared(queries.names, database.names)
            return groundtruth_from_scores(name, database, queries, depth, self._score_block(counts))
        if context.sfm is None:
            raise ValueError(f"ground truth {name!r}: co-observation needs the sfm settings")
        if context.cache_dir is None:
            with tempfile.TemporaryDirectory(prefix="co_observation-") as folder:
                in_folder = dataclasses.replace(context, cache_dir=Path(folder))
                return self.groundtruth(database, queries, depth, name, in_folder)
        shared = shared_points(database, queries, Path(context.cache_dir), context.sfm, self.query_pairs)
        return groundtruth_from_scores(name, database, queries, depth, self._score_block(shared))

    def _score_block(self, shared: sparse.csr_matrix):
        """The `ScoreBlock` of ``shared`` ``[Q, N]`` point counts: ranked by them where > 0, relevant
        from ``min_shared``."""

        def score_block(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            counts = shared[rows].toarray().astype(np.float64)
            return counts, counts > 0, counts >= self.min_shared

        return score_block

    def sfm_pairs(
        self, database: ImageSet, queries: ImageSet, context: DefinitionContext
    ) -> tuple[list[tuple[str, str]], list[tuple[str, str]]]:
        """The database pairs and the (query, database) pairs (names) `groundtruth` matches: none
        with a reconstruction's tracks (``context.observations``)."""
        if context.observations is not None:
            return [], []
        database_rows, query_rows = joint_map_pairs(database, queries, context.sfm, self.query_pairs)
        return (
            [(database.names[a], database.names[b]) for a, b in database_rows],
            [(queries.names[q], database.names[t]) for q, t in query_rows],
        )

    def graded(self, images: ImageSet, context: DefinitionContext) -> GradedRows:
        """The share of each row image's 3D points that the other image observes too, where they
        share at least ``min_shared``; else 0. The points are those of ``context.world``'s
        reconstruction (`Scene.observations`) when it has one, else of its known-pose map
        (`database_co_observations`; ``images``: its database)."""
        world = context.world
        if world is not None and world.observations is not None:
            counts = world.observations.shared(images.names, images.names)
        elif world is None or context.sfm is None or context.cache_dir is None:
            raise ValueError(
                f"{context.key}: co-observation training relevance needs the world's known-pose map "
                "(DefinitionContext world, sfm and cache_dir)"
            )
        elif list(world.database.names) != list(images.names):
            raise ValueError(f"{context.key}: the images graded are not the database of scene {world.name!r}")
        else:
            counts = database_co_observations(world, context.sfm, context.cache_dir)

        def grade(rows: np.ndarray) -> np.ndarray:
            shared = counts[rows].toarray().astype(np.float64)
            own = np.maximum(shared[np.arange(len(rows)), rows], 1.0)[:, None]
            return np.where(shared >= self.min_shared, shared / own, 0.0)

        return grade


def co_observation_groundtruth(
    database: ImageSet,
    queries: ImageSet,
    *,
    depth: int,
    min_shared: int,
    query_pairs: int,
    sfm: SfmSettings,
    cache_dir: str | Path | None = None,
    name: str = "gt_co_observation",
) -> GroundTruth:
    """`CoObservationDefinition.groundtruth` of these parameters, by keyword."""
    context = DefinitionContext(sfm=sfm, cache_dir=Path(cache_dir) if cache_dir is not None else None)
    return CoObservationDefinition(min_shared, query_pairs).groundtruth(database, queries, depth, name, context)


def shared_points(
    database: ImageSet, queries: ImageSet, cache_dir: Path, sfm: SfmSettings, query_pairs: int
) -> sparse.csr_matrix:
    """``[Q, N]`` number of joint-map points observed by query q and database image t
    (zero rows for queries without a pose)."""
    posed = np.flatnonzero(queries.has_pose)
    workers = sfm.processes
    # features and matches of the whole image sets: the caches of the SfM paradigms
    database_features = extract_features(database, sfm.features, cache_dir, workers)
    query_features = extract_features(queries, sfm.features, cache_dir, workers)
    database_matcher = PairMatcher(database, database_features, database, database_features, sfm.matching, cache_dir)
    query_matcher = PairMatcher(queries, query_features, database, database_features, sfm.matching, cache_dir)

    database_pair_rows, query_pair_rows = joint_map_pairs(database, queries, sfm, query_pairs)
    named_database = [(database.names[a], database.names[b]) for a, b in database_pair_rows]
    named_queries = [(queries.names[q], database.names[t]) for q, t in query_pair_rows]
    verification = sfm.database_verification  # queries with a reference pose: verified by it too
    database_matcher.ensure(named_database, workers, verification)
    query_matcher.ensure(named_queries, workers, verification)
    database_matches = database_matcher.load(named_database, verification)
    query_matches = query_matcher.load(named_queries, verification)

    # joint image order: database 0..N-1, then the posed queries (`overlapping_pairs` pairs only those)
    offset = len(database)
    joint_query = offset + np.searchsorted(posed, query_pair_rows[:, 0])
    matches = {(int(a), int(b)): database_matches[pair] for (a, b), pair in zip(database_pair_rows, named_database)}
    matches.update(
        {
            (int(t), int(j)): query_matches[pair][:, ::-1]
            for j, t, pair in zip(joint_query, query_pair_rows[:, 1], named_queries)
        }
    )
    posed_names = [queries.names[q] for q in posed]
    keypoints = database_features.keypoints(database.names)
    query_keypoints = query_features.keypoints(posed_names)
    joint: SparseMap = sfm.triangulation.triangulate(
        database.cameras + [queries.cameras[q] for q in posed],
        np.concatenate([database.qvec, queries.qvec[posed]]),
        np.concatenate([database.tvec, queries.tvec[posed]]),
        [keypoints[n] for n in database.names] + [query_keypoints[n] for n in posed_names],
        matches,
    )
    observed = _incidence(joint.observed_points(), joint.num_points)
    counts = (observed[offset:] @ observed[:offset].T).tocoo()
    return sparse.csr_matrix((counts.data, (posed[counts.row], counts.col)), shape=(len(queries), len(database)))


def joint_map_pairs(
    database: ImageSet, queries: ImageSet, sfm: SfmSettings, query_pairs: int
) -> tuple[np.ndarray, np.ndarray]:
    """The image pairs of the joint map, by index: database pairs ``[m, 2]`` (those of the global
    map, ``sfm.map_pairs``) and (query, database) pairs ``[n, 2]``, each posed query with its
    ``query_pairs`` most overlapping database images."""
    query_selection = dataclasses.replace(sfm.map_pairs, max_per_image=query_pairs)
    return (
        database_pairs(database, sfm.map_pairs),
        overlapping_pairs(queries, database, query_selection, exclude_self=False),
    )


def database_co_observations(scene: Scene, sfm: SfmSettings, cache_dir: Path) -> sparse.csr_matrix:
    """``[N, N]`` number of 3D points of the database's known-pose map (paradigm 2b's global map,
    the same cache) observed by both database images; the diagonal: the points each observes."""
    sparse_map = global_map(SfmInputs.prepare(scene, sfm, Path(cache_dir)), None, Path(cache_dir))
    observed = _incidence(sparse_map.observed_points(), sparse_map.num_points)
    return (observed @ observed.T).tocsr()


def _incidence(points_per_image: list[np.ndarray], num_points: int) -> sparse.csr_matrix:
    """Binary ``[images, points]`` matrix: image i observes point p."""
    rows = np.repeat(np.arange(len(points_per_image)), [len(p) for p in points_per_image])
    columns = np.concatenate(points_per_image) if points_per_image else np.empty(0, dtype=np.int64)
    return sparse.csr_matrix(
        (np.ones(len(rows), dtype=np.int64), (rows, columns)), shape=(len(points_per_image), num_points)
    )
