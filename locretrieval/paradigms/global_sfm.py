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
from typing import ClassVar

import numpy as np
from filelock import FileLock

from locretrieval.cache import config_key, tree_signature
from locretrieval.paradigms.sfm import Localize, SfmParadigm
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene
from locretrieval.sfm.colmap_model import missing_model_files, read_colmap_map
from locretrieval.sfm.features import extract_features
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.pairs import database_pairs
from locretrieval.sfm.pnp import EMPTY_RETRIEVAL, NO_3D_POINTS
from locretrieval.sfm.pose_cache import Outcome, PoseCache
from locretrieval.sfm.query_tasks import QueryTask, outcomes_per_image_set
from locretrieval.sfm.registration import register_query
from locretrieval.sfm.settings import SfmSettings
from locretrieval.sfm.sparse_map import SparseMap
from locretrieval.sfm.work import Work, database_pair_work

log = logging.getLogger(__name__)

#: Bump when the meaning of cached maps changes.
CACHE_VERSION = 1


@dataclass
class GlobalSfm(SfmParadigm):
    """Paradigm 2b (``configs/paradigms/global_sfm.yaml``). ``colmap_model``: an existing COLMAP
    model folder built from the same features (e.g. a published ``colmap-sfm`` map), or ``None``:
    triangulate the database pairs of ``sfm.map_pairs``. What it needs: the global map, then each
    query registered in it."""

    colmap_model: str | None
    label: ClassVar[str] = "global_sfm"
    shared_map: ClassVar[bool] = True

    def missing_inputs(self) -> list[str]:
        """The files of ``colmap_model`` that are absent, if one is given."""
        if not self.colmap_model:
            return []
        return [f"colmap_model: {problem}" for problem in missing_model_files(self.colmap_model)]

    def shared_map_pairs(self, inputs: SfmInputs) -> list[tuple[str, str]]:
        """The database pairs of the global map (`database_pairs` of ``sfm.map_pairs``), unless the
        map is cached or an existing COLMAP model."""
        if self.colmap_model or map_cache_path(inputs, inputs.cache_dir).exists():
            return []
        database = inputs.scene.database
        return [(database.names[a], database.names[b]) for a, b in database_pairs(database, inputs.map_pairs)]

    def triangulate_shared_map(self, inputs: SfmInputs) -> None:
        """The global map triangulated (or read) and cached once, before any query is registered."""
        global_map(inputs, self.colmap_model, inputs.cache_dir)

    def pose_cache(self, inputs: SfmInputs) -> PoseCache:
        """The registration outcomes, keyed by the map (its cache file, or the COLMAP model's files)."""
        model = self.colmap_model
        source = [model, tree_signature(model)] if model else map_cache_path(inputs, inputs.cache_dir).stem
        return inputs.pose_cache("global_sfm", [CACHE_VERSION, source], inputs.cache_dir)

    def registration(self, inputs: SfmInputs) -> tuple[Localize, tuple[SfmInputs, SparseMap]]:
        """Each query registered in the global map (`register_query_in_map`)."""
        return register_query_in_map, (inputs, global_map(inputs, self.colmap_model, inputs.cache_dir))

    def count_maps(
        self,
        inputs: SfmInputs,
        rankings: Sequence[Ranking] | None,
        tasks: Sequence[QueryTask] | None,
        num_rankings: int,
    ) -> tuple[Work, Work, float]:
        """The map's database pairs, exact either way (from the known poses) unless the map is
        cached or given."""
        if self.colmap_model or map_cache_path(inputs, inputs.cache_dir).exists():
            return Work(0, 0), Work(1, 0), 0
        map_pairs = database_pair_work(inputs, self.shared_map_pairs(inputs))
        return map_pairs, Work(1, 1), map_pairs.total

    def map_points(self, scene: Scene, sfm: SfmSettings, cache_dir: Path) -> np.ndarray | None:
        """The 3D points of the global map `run` used: the ``colmap_model``'s, or the triangulated
        map cached in ``cache_dir``; ``None`` when it was not built."""
        if self.colmap_model:
            import pycolmap

            model = pycolmap.Reconstruction(self.colmap_model)
            return np.array([point.xyz for point in model.points3D.values()], dtype=np.float64).reshape(-1, 3)
        path = map_cache_path(SfmInputs.prepare(scene, sfm, Path(cache_dir), extract=False), Path(cache_dir))
        return SparseMap.load(path).points if path.exists() else None


def global_map(inputs: SfmInputs, colmap_model: str | None, cache_dir: Path) -> SparseMap:
    """The database's map: an existing COLMAP model, or triangulated with known poses (cached, and
    memory-mapped from the cache: a worker registering a query reads only what its top-k images see)."""
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
            return SparseMap.load(path, memory_map=True)
        pairs = database_pairs(database, inputs.map_pairs)
        named = [(database.names[a], database.names[b]) for a, b in pairs]
        workers = inputs.settings.processes
        extract_features(database, inputs.settings.features, inputs.cache_dir, workers)  # where the inputs read them
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
    return SparseMap.load(path, memory_map=True)


def map_cache_path(inputs: SfmInputs, cache_dir: Path) -> Path:
    """Where the triangulated map is cached: keyed by its pose-verified matches' store (whose
    name encodes the features, the ratio, the epipolar bound and the database poses), the
    triangulation settings and the pair selection."""
    matches = inputs.database_pairs.store(inputs.database_verification).folder.name
    key = config_key(CACHE_VERSION, matches, inputs.settings.triangulation.identity(), asdict(inputs.map_pairs))
    return cache_dir / "maps" / f"{key}.npz"


def register_query_in_map(shared: tuple[SfmInputs, SparseMap], task: QueryTask) -> list[list[Outcome]]:
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
