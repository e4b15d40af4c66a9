"""The SfM paradigms as one pipeline of explicit stages, driven once for every enabled SfM paradigm.

Each stage runs over the whole scene and every ranking at once, and hands the next one its
results through the caches:

1. **features**: local features of both image sets (`extract_features`, ``sfm.features``);
2. **match + verify**: every query pair any paradigm needs (each query with its top ``max(k)``
   images of every ranking, verified per ``sfm.matching.query_verification``) and every database
   pair of any map (pose-verified), each store filled in one pass (`PairMatcher.ensure`: CPU
   workers, or the GPU fed by them);
3. **triangulate + register**: each paradigm's `SfmStages.localize`, per query in worker processes
   (a local map is triangulated and the query registered in it at once; the global map once).

`run_sfm` is the driver. The paradigms say what they need (`SfmStages`) and never match anything
themselves, so one evaluation matches each store once.

**Shards** (``sfm.shard=i/n``, e.g. a Hydra multirun over ``0/n,...,n-1/n`` on the joblib or
submitit launcher): job ``i`` does every ``n``-th item of each stage's sorted work (images,
database pairs, queries with their pairs, maps and registrations), then computes whatever of its
own later stages' inputs is still missing (another job's share that has not been written yet:
computed twice, never wrong). A map all queries share (the global map) is built by the first job
that needs it, under a file lock, and read by the others. The caches are content-addressed and
safe for concurrent writers, so a plain run afterwards finds every pair, map and pose in them.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from locretrieval.localization.estimates import PoseEstimates
from locretrieval.localization.features import extract_features
from locretrieval.localization.paradigm import ParadigmSettings
from locretrieval.localization.sfm import SfmInputs, SfmSettings
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene

log = logging.getLogger(__name__)

Pair = tuple[str, str]


@dataclass(frozen=True)
class SfmStages:
    """What an SfM paradigm adds to the pipeline (its module's functions):

    - ``shared_map_pairs(inputs, settings) -> [pair]``: the database pairs of maps every query
      uses (the global map), to be matched and pose-verified;
    - ``query_map_pairs(inputs, rankings, ks, settings, queries) -> [pair]``: those of maps built
      per query, for ``queries`` (None: all);
    - ``localize(inputs, rankings, ks, settings, cache_dir, queries) -> [PoseEstimates]``: its
      triangulate and register stage; with ``queries`` (a shard's) those are localised and cached
      only, and None is returned.
    """

    shared_map_pairs: Callable[[SfmInputs, Any], list[Pair]]
    query_map_pairs: Callable[[SfmInputs, Sequence[Ranking], list[list[int]], Any, Sequence[int] | None], list[Pair]]
    localize: Callable[..., list[PoseEstimates] | None]


def run_sfm(
    scene: Scene, rankings: Sequence[Ranking], paradigms: Mapping[str, tuple[SfmStages, ParadigmSettings]],
    sfm: SfmSettings, cache_dir: str | Path | None, timings: dict[str, float] | None = None,
) -> dict[str, list[PoseEstimates]] | None:
    """Every SfM paradigm of ``paradigms`` (name -> its stages and settings) on every ranking:
    the pose estimates by paradigm, or None for a job of ``sfm.shard`` (its share cached only).
    The seconds each stage took are logged, and put in ``timings`` when it is given."""
    if cache_dir is None:
        raise ValueError(f"{' and '.join(paradigms)} need a cache directory for their features, matches and maps")
    cache_dir = Path(cache_dir)
    shard = sfm.job_shard
    inputs = SfmInputs.prepare(scene, sfm, cache_dir, extract=False)
    ks = {name: [ranking.clamp_ks(settings.k) for ranking in rankings] for name, (_, settings) in paradigms.items()}
    deepest = [[max(max(ks[name][r]) for name in paradigms)] for r in range(len(rankings))]
    queries = None if shard is None else shard.take(range(len(scene.queries)))
    query_pairs = inputs.ranked_pairs(rankings, deepest, queries)
    map_pairs = inputs.database_pairs.canonical(
        pair for name, (stages, settings) in paradigms.items()
        for pair in [*stages.shared_map_pairs(inputs, settings), *stages.query_map_pairs(inputs, rankings, ks[name], settings, None)]
    )
    if shard is not None:
        log.info("SfM shard %s: %d of %d queries, %d of %d database pairs", shard, len(queries), len(scene.queries),
                 len(shard.take(map_pairs)), len(map_pairs))
        map_pairs = shard.take(map_pairs)
    clock = StageClock(timings)
    with clock("features"):
        extract_stage(inputs, cache_dir, shard, query_pairs, map_pairs)
    with clock("match + verify"):
        match_stage(inputs, query_pairs, map_pairs)
        if shard is not None:  # this job's maps' pairs that another job's share holds and has not written yet
            own_maps = [pair for name, (stages, settings) in paradigms.items() for pair in stages.query_map_pairs(inputs, rankings, ks[name], settings, queries)]
            extract_stage(inputs, cache_dir, shard, [], own_maps, whole_sets=False)
            inputs.database_pairs.ensure(own_maps, sfm.processes, inputs.database_verification)
    estimates = {}
    for name, (stages, settings) in paradigms.items():
        with clock(f"{name}: triangulate + register"):
            estimates[name] = stages.localize(inputs, rankings, ks[name], settings, cache_dir, queries)
    log.info("SfM stages: %s", ", ".join(f"{stage} {seconds:.1f} s" for stage, seconds in clock.seconds.items()))
    return None if shard is not None else estimates


class StageClock:
    """Seconds per stage: ``with clock(stage): ...``, kept in ``timings`` when it is given."""

    def __init__(self, timings: dict[str, float] | None) -> None:
        self.seconds = timings if timings is not None else {}

    @contextlib.contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        started = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] = time.perf_counter() - started


def extract_stage(
    inputs: SfmInputs, cache_dir: Path, shard: Any, query_pairs: Sequence[Pair], database_pairs: Sequence[Pair], whole_sets: bool = True
) -> None:
    """Local features of every image of both sets (``whole_sets``; a shard's share of each), then
    of the images of the (query, database) and (database, database) pairs still missing."""
    scene, settings, workers = inputs.scene, inputs.settings, inputs.settings.processes
    needed = (
        (scene.database, sorted({name for _, name in query_pairs} | {name for pair in database_pairs for name in pair})),
        (scene.queries, sorted({query for query, _ in query_pairs})),
    )
    for images, names in needed:
        if whole_sets:
            extract_features(images, settings.features, cache_dir, workers, None if shard is None else shard.take(images.names))
        extract_features(images, settings.features, cache_dir, workers, names)


def match_stage(inputs: SfmInputs, query_pairs: Sequence[Pair], database_pairs: Sequence[Pair]) -> None:
    """Match and verify every query pair and every database pair (each store in one pass)."""
    workers = inputs.settings.processes
    inputs.query_pairs.ensure(query_pairs, workers, inputs.query_verification)
    inputs.database_pairs.ensure(database_pairs, workers, inputs.database_verification)
