"""Paradigm 2b, global SfM (paper Sec. 3.3 and 3.9): register queries in one map of the database.

The global map is either

- triangulated from the database with its known poses: database pairs selected by frustum
  overlap (`database_pairs`: the pairs whose truncated frusta inscribe a sphere of radius
  above ``sfm.map_pairs.min_radius`` metres, at most the ``max_per_image`` most overlapping per
  image; the paper used radius >= 10 m, or the 50 most overlapping for dense sets), matched,
  verified against the known poses' epipolar geometry and triangulated with COLMAP's
  triangulator; built once per scene, features and options, and cached in
  ``<cache_dir>/maps/``; or
- an existing COLMAP model (``global_sfm.colmap_model``, e.g. the published ``colmap-sfm`` maps),
  whose 2D points must be the configured features (`read_colmap_map`).

Each query is matched to its top-k images (cached pairs, verified per
``matching.query_verification``); the map points observed by the matched database keypoints
give 2D-3D correspondences, and LO-RANSAC P3P with refinement gives its pose. Outcomes are
cached in ``<cache_dir>/poses/`` by query and image set (`PoseCache`), keyed by the map, the
query matches' store and the PnP settings.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from filelock import FileLock

from locretrieval.cache import config_key, tree_signature
from locretrieval.localization.colmap_model import missing_model_files, read_colmap_map
from locretrieval.localization.estimates import PoseEstimates
from locretrieval.localization.features import extract_features
from locretrieval.localization.pairs import database_pairs
from locretrieval.localization.paradigm import ParadigmSettings
from locretrieval.localization.pipeline import SfmStages, run_sfm
from locretrieval.localization.plan import (
    ParadigmWork,
    Work,
    database_pair_work,
    queries_to_register,
    query_pair_work,
    registration_bound,
    registration_work,
)
from locretrieval.localization.pnp import EMPTY_RETRIEVAL, NO_3D_POINTS
from locretrieval.localization.pose_cache import PoseCache
from locretrieval.localization.sfm import (
    SFM_METHOD,
    Outcome,
    QueryTask,
    SfmInputs,
    SfmSettings,
    outcomes_per_image_set,
    query_tasks,
    register_query,
    run_queries,
)
from locretrieval.localization.sparse_map import SparseMap
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene

log = logging.getLogger(__name__)

#: Bump when the meaning of cached maps changes.
CACHE_VERSION = 1


@dataclass
class GlobalSfmSettings(ParadigmSettings):
    """``colmap_model``: an existing COLMAP model folder built from the same features (e.g. a
    published ``colmap-sfm`` map), or ``None``: triangulate the database pairs of ``sfm.map_pairs``."""

    colmap_model: str | None

    def method_names(self) -> list[str]:
        return [SFM_METHOD]


def missing_inputs(settings: GlobalSfmSettings) -> list[str]:
    """The files of ``colmap_model`` that are absent, if one is given."""
    if not settings.colmap_model:
        return []
    return [f"colmap_model: {problem}" for problem in missing_model_files(settings.colmap_model)]


def run(
    scene: Scene, rankings: Sequence[Ranking], settings: GlobalSfmSettings, sfm: SfmSettings, cache_dir: Path | None
) -> list[PoseEstimates] | None:
    """Paradigm entry point: the pose of every query for every ranking and every ``settings.k``
    (through the SfM pipeline, `run_sfm`, with this paradigm alone)."""
    estimates = run_sfm(scene, rankings, {"global_sfm": (STAGES, settings)}, sfm, cache_dir)
    return None if estimates is None else estimates["global_sfm"]


def shared_map_pairs(inputs: SfmInputs, settings: GlobalSfmSettings) -> list[tuple[str, str]]:
    """The database pairs of the global map (`database_pairs` of ``sfm.map_pairs``), unless the
    map is cached or an existing COLMAP model."""
    if settings.colmap_model or map_cache_path(inputs, inputs.cache_dir).exists():
        return []
    database = inputs.scene.database
    return [(database.names[a], database.names[b]) for a, b in database_pairs(database, inputs.map_pairs)]


def query_map_pairs(
    inputs: SfmInputs, rankings: Sequence[Ranking], ks, settings: GlobalSfmSettings, queries
) -> list[tuple[str, str]]:
    """None: the global map is every query's."""
    return []


def localize(
    inputs: SfmInputs,
    rankings: Sequence[Ranking],
    ks: Sequence[list[int]],
    settings: GlobalSfmSettings,
    cache_dir: Path,
    queries: Sequence[int] | None,
) -> list[PoseEstimates] | None:
    """Triangulate (the global map, once) and register every query in it (in worker processes)."""
    sparse_map = global_map(inputs, settings.colmap_model, cache_dir)
    cache = _pose_cache(inputs, settings, cache_dir)
    return run_queries(
        "global_sfm", rankings, ks, localize_query, (inputs, sparse_map), inputs.settings.processes, cache, queries
    )


def plan(
    scene: Scene,
    rankings: Sequence[Ranking] | None,
    settings: GlobalSfmSettings,
    sfm: SfmSettings,
    cache_dir: Path,
    num_rankings: int,
) -> ParadigmWork:
    """The work of `run` (`ParadigmWork`), without doing any: exact for ``rankings``, upper
    bounds for ``num_rankings`` rankings not computed yet (``None``). The map's database pairs
    are exact either way (from the known poses) unless the map is cached or given."""
    inputs = SfmInputs.prepare(scene, sfm, cache_dir, extract=False)
    query_pairs = query_pair_work(inputs, rankings, settings.k, num_rankings)
    if settings.colmap_model or map_cache_path(inputs, cache_dir).exists():
        map_pairs, maps = Work(0, 0), Work(1, 0)
    else:
        pairs = database_pairs(scene.database, inputs.map_pairs)
        map_pairs = database_pair_work(inputs, [(scene.database.names[a], scene.database.names[b]) for a, b in pairs])
        maps = Work(1, 1)
    if rankings is None:
        return ParadigmWork(
            "global_sfm",
            query_pairs,
            map_pairs,
            maps,
            map_pairs.total,
            *registration_bound(len(scene.queries), len(scene.database), settings.k, num_rankings),
            Work(len(scene.queries), len(scene.queries)),
            parallel_maps=False,
        )
    tasks = query_tasks(
        rankings, [ranking.clamp_ks(settings.k) for ranking in rankings], _pose_cache(inputs, settings, cache_dir)
    )
    return ParadigmWork(
        "global_sfm",
        query_pairs,
        map_pairs,
        maps,
        map_pairs.total,
        *registration_work(tasks),
        queries_to_register(tasks),
        parallel_maps=False,
    )


def triangulate(inputs: SfmInputs, settings: GlobalSfmSettings, cache_dir: Path) -> None:
    """The global map's stage: triangulated (or read) and cached once, before any query is registered."""
    global_map(inputs, settings.colmap_model, cache_dir)


#: This paradigm's stages of the SfM pipeline: the global map, then each query registered in it.
STAGES = SfmStages(shared_map_pairs, query_map_pairs, triangulate, localize, "register", plan)


def _pose_cache(inputs: SfmInputs, settings: GlobalSfmSettings, cache_dir: Path) -> PoseCache:
    """The registration outcomes, keyed by the map (its cache file, or the COLMAP model's files)."""
    model = settings.colmap_model
    source = [model, tree_signature(model)] if model else map_cache_path(inputs, cache_dir).stem
    return inputs.pose_cache("global_sfm", [CACHE_VERSION, source], cache_dir)


def global_map(inputs: SfmInputs, colmap_model: str | None, cache_dir: Path) -> SparseMap:
    """The database's map: an existing COLMAP model, or triangulated with known poses (cached)."""
    database = inputs.scene.database
    if colmap_model:
        log.info("global map: COLMAP model %s", colmap_model)
        keypoints = inputs.database_features.keypoints(database.names)
        return read_colmap_map(colmap_model, database.names, [keypoints[n] for n in database.names])
    path = map_cache_path(inputs, cache_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(f"{path}.lock"):  # one builder among the jobs sharing the cache (shards); the others wait and read it
        if path.exists():
            log.info("global map loaded from %s", path)
            return SparseMap.load(path)
        pairs = database_pairs(database, inputs.map_pairs)
        named = [(database.names[a], database.names[b]) for a, b in pairs]
        workers = inputs.settings.processes
        extract_features(database, inputs.settings.features, cache_dir, workers)
        inputs.database_pairs.ensure(named, workers, inputs.database_verification)
        matches = inputs.database_pairs.load(named, inputs.database_verification)
        keypoints = inputs.database_features.keypoints(database.names)
        sparse_map = inputs.settings.triangulation.triangulate(
            database.cameras,
            database.qvec,
            database.tvec,
            [keypoints[n] for n in database.names],
            {(int(a), int(b)): matches[pair] for (a, b), pair in zip(pairs, named)},
        )
        sparse_map.save(path)
    log.info(
        "global map: %d points from %d database images (%d pairs), saved to %s",
        sparse_map.num_points,
        len(database),
        len(pairs),
        path,
    )
    return sparse_map


def map_cache_path(inputs: SfmInputs, cache_dir: Path) -> Path:
    """Where the triangulated map is cached: keyed by its pose-verified matches' store (whose
    name encodes the features, the ratio, the epipolar bound and the database poses), the
    triangulation settings and the pair selection."""
    matches = inputs.database_pairs.store(inputs.database_verification).folder.name
    key = config_key(CACHE_VERSION, matches, inputs.settings.triangulation.identity(), asdict(inputs.map_pairs))
    return cache_dir / "maps" / f"{key}.npz"


def map_points(scene: Scene, settings: GlobalSfmSettings, sfm: SfmSettings, cache_dir: Path) -> np.ndarray | None:
    """The 3D points ``[P, 3]`` (world coordinates, metres) of the global map `run` used: the
    ``colmap_model``'s, or the triangulated map cached in ``cache_dir``; ``None`` when it was
    not built (nothing is computed here)."""
    if settings.colmap_model:
        import pycolmap

        model = pycolmap.Reconstruction(settings.colmap_model)
        return np.array([point.xyz for point in model.points3D.values()], dtype=np.float64).reshape(-1, 3)
    path = map_cache_path(SfmInputs.prepare(scene, sfm, Path(cache_dir), extract=False), Path(cache_dir))
    return SparseMap.load(path).points if path.exists() else None


def localize_query(shared: tuple[SfmInputs, SparseMap], task: QueryTask) -> list[list[Outcome]]:
    """Outcomes ``[ranking][k]`` of one query registered in the global map, once per distinct
    set of top-k images whose outcome is not known (the correspondences depend on the set only)."""
    inputs, sparse_map = shared
    images = sorted({i for selected in task.pending() for i in selected})
    query_keypoints, query_matches = inputs.query_matches(task.query, images)
    slots = {i: i for i in images}

    def localize(selected: tuple[int, ...]) -> Outcome:
        if not selected:
            return EMPTY_RETRIEVAL
        if not any((sparse_map.observations[i] >= 0).any() for i in selected):
            return NO_3D_POINTS
        return register_query(
            inputs, task.query, query_keypoints, {i: query_matches[i] for i in selected}, sparse_map, slots
        )

    return outcomes_per_image_set(task, localize)
