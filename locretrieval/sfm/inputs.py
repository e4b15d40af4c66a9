"""The caches the SfM paradigms (2a local, 2b global) read (`SfmInputs`): local features of both image
sets, the matches of query and database pairs, the union of query-database pairs over all rankings
and the registration outcomes.

Every ranking is handled in the same run so that features and matches are shared: the query
pairs are the union over rankings of each query with its top ``max(k)`` database images, each
matched once; the per-query work then reads only cached inputs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from locretrieval.cache import config_key
from locretrieval.retrieval import EMPTY, Ranking
from locretrieval.scene import Scene
from locretrieval.sfm.features import FeatureStore, extract_features, feature_store
from locretrieval.sfm.matching import PairMatcher
from locretrieval.sfm.pairs import PairSelection
from locretrieval.sfm.pose_cache import PoseCache
from locretrieval.sfm.settings import SfmSettings
from locretrieval.sfm.verification import PairVerification


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


def sfm_inputs(scene: Scene, sfm: SfmSettings, cache_dir: str | Path | None, paradigms: Iterable[str]) -> SfmInputs:
    """The caches the SfM ``paradigms`` of a run share (`SfmInputs`), named once for the run."""
    if cache_dir is None:
        raise ValueError(f"{' and '.join(paradigms)} need a cache directory for their features, matches and maps")
    return SfmInputs.prepare(scene, sfm, Path(cache_dir), extract=False)
