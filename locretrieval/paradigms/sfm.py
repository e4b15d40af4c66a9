"""The SfM paradigms (2a local, 2b global) on the verbs of `locretrieval.sfm`: an `SfmParadigm` says
which pairs, maps and registrations it needs; `run_sfm` runs every enabled one in one pass of the
verbs, and `count_work` counts their work without doing any.

The stages of `run_sfm` hand each other their results through the caches:

1. **features** (`extract_pair_features`): local features of both image sets;
2. **match + verify** (`match_and_verify`: CPU workers, or the GPU fed by them): the database
   pairs of the maps every query shares (the global map), then, per chunk of queries, each
   query with its top ``max(k)`` images of every ranking (verified per
   ``sfm.query_verification``) and the database pairs of its local maps (pose-verified);
3. **triangulate** (``<paradigm>: triangulate``): the maps every query shares (the global map,
   `SfmParadigm.triangulate_shared_map`) once, in this process, before any query; the maps of
   each query (local maps, `SfmParadigm.triangulate_query_maps`) per chunk, in worker processes;
   both cached;
4. **register** (``<paradigm>: register``, `SfmParadigm.register`): each query of a chunk in its
   maps, in worker processes, outcomes cached.

The queries stream in chunks (`stream_chunks`): while one chunk is triangulated and registered
the next one is matched (on a GPU the two stages then overlap); every outcome is gathered from the
cache at the end. The paradigms say what they need and never match anything themselves, so one
evaluation matches each pair once.

**Shards** (the job's ``shard=i/n``, `locretrieval.shard.Shard`; e.g. a Hydra multirun over
``0/n,...,n-1/n`` on the joblib or submitit launcher): job ``i`` does every ``n``-th item of
each stage's sorted work (images, database pairs, queries with their pairs, maps and
registrations), then computes whatever of its own later stages' inputs is still missing (another
job's share that has not been written yet: computed twice, never wrong). A map all queries share
(the global map) is built by the first job that needs it, under a file lock, and read by the
others. The caches are content-addressed and safe for concurrent writers, so a plain run
afterwards finds every pair, map and pose in them.
"""

from __future__ import annotations

import abc
import dataclasses
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

from locretrieval.estimates import PoseEstimates
from locretrieval.paradigms.base import Paradigm
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene
from locretrieval.sfm.inputs import SfmInputs, sfm_inputs
from locretrieval.sfm.pipeline import (
    Pair,
    SfmRun,
    StageMeter,
    extract_pair_features,
    match_and_verify,
    stream_chunks,
)
from locretrieval.sfm.pose_cache import Outcome, PoseCache
from locretrieval.sfm.query_tasks import QueryTask, query_tasks
from locretrieval.sfm.registration import SFM_METHOD, register_queries
from locretrieval.sfm.settings import SfmSettings
from locretrieval.sfm.work import (
    FEATURES,
    MATCHING,
    ParadigmWork,
    SfmPlan,
    Work,
    feature_work,
    queries_to_register,
    query_pair_work,
    registration_bound,
    registration_work,
    stage_names,
)
from locretrieval.shard import Shard

log = logging.getLogger(__name__)

#: What registers one query in a worker process: ``localize(shared, task)``, its outcomes ``[ranking][k]``.
Localize = Callable[[Any, QueryTask], list[list[Outcome]]]


@dataclass
class SfmParadigm(Paradigm):
    """A paradigm whose work is SfM: it says what it needs and does its maps and registrations with
    the verbs of `locretrieval.sfm`; `run_sfm` runs it with every other enabled one (run alone, it is
    `run_sfm` with itself only). ``label``: its estimates' paradigm name there.

    - `shared_map_pairs`: the database pairs of maps every query uses (the global map), to be
      matched and pose-verified; `query_map_pairs`: those of maps built per query;
    - the stage ``<paradigm>: triangulate``: `triangulate_shared_map` triangulates (and caches)
      the maps every query uses, in this process, once their pairs are matched and before any
      query; `triangulate_query_maps` those of each query of a chunk, in worker processes (each
      a no-op for a paradigm without such maps);
    - the stage ``<paradigm>: register``: `register` registers each query of a chunk in its maps
      (`registration`, in worker processes), outcomes cached (`pose_cache`), and gathers them at the end;
    - `count`: its work, counted without doing any (`locretrieval.sfm.work`; its maps' by `count_maps`).
    """

    label: ClassVar[str]
    uses_sfm: ClassVar[bool] = True
    #: Whether its map is one every query shares (else each query has its own).
    shared_map: ClassVar[bool] = False

    def method_names(self) -> list[str]:
        return [SFM_METHOD]

    def shared_map_pairs(self, inputs: SfmInputs) -> list[Pair]:
        """The database pairs of the maps every query uses (default: none)."""
        return []

    def query_map_pairs(
        self, inputs: SfmInputs, rankings: Sequence[Ranking], ks: Sequence[list[int]], queries: Sequence[int] | None
    ) -> list[Pair]:
        """The database pairs of the maps built per query, for ``queries`` (None: all; default: none)."""
        return []

    def triangulate_shared_map(self, inputs: SfmInputs) -> None:
        """Triangulate (and cache) the maps every query uses (default: there are none)."""

    def triangulate_query_maps(
        self, inputs: SfmInputs, rankings: Sequence[Ranking], ks: Sequence[list[int]], queries: Sequence[int]
    ) -> None:
        """Triangulate (and cache) the maps of each of ``queries`` whose registrations are not
        cached (default: there are none)."""

    @abc.abstractmethod
    def pose_cache(self, inputs: SfmInputs) -> PoseCache:
        """Its registration outcomes (`SfmInputs.pose_cache`), keyed by what its maps are keyed by."""

    @abc.abstractmethod
    def registration(self, inputs: SfmInputs) -> tuple[Localize, Any]:
        """``(localize, shared)``: what registers one query in its maps in a worker process, and what
        every such task reads (picklable)."""

    @abc.abstractmethod
    def count_maps(
        self,
        inputs: SfmInputs,
        rankings: Sequence[Ranking] | None,
        tasks: Sequence[QueryTask] | None,
        num_rankings: int,
    ) -> tuple[Work, Work, float]:
        """``(database pairs, maps, matched pairs per map)`` of its maps, without building any: exact
        for ``rankings`` (their ``tasks``), upper bounds for ``num_rankings`` rankings not computed
        yet (both ``None``)."""

    def register(
        self, inputs: SfmInputs, rankings: Sequence[Ranking], ks: Sequence[list[int]], queries: Sequence[int] | None
    ) -> list[PoseEstimates] | None:
        """With ``queries`` (a chunk, or a shard's), register those in their maps (triangulated by
        then; `register_queries`, in worker processes) and cache the outcomes only, returning None;
        with None, gather every outcome (cached by then) as estimates."""
        localize, shared = self.registration(inputs)
        processes = inputs.settings.processes
        return register_queries(self.label, rankings, ks, localize, shared, processes, self.pose_cache(inputs), queries)

    def count(self, inputs: SfmInputs, rankings: Sequence[Ranking] | None, num_rankings: int) -> ParadigmWork:
        """Its work (`ParadigmWork`), without doing any: exact for ``rankings``, upper bounds for
        ``num_rankings`` rankings not computed yet (``None``)."""
        scene, tasks = inputs.scene, None
        query_pairs = query_pair_work(inputs, rankings, self.k, num_rankings)
        if rankings is None:
            registrations = registration_bound(len(scene.queries), len(scene.database), self.k, num_rankings)
            queries = Work(len(scene.queries), len(scene.queries))
        else:
            tasks = query_tasks(rankings, [ranking.clamp_ks(self.k) for ranking in rankings], self.pose_cache(inputs))
            registrations, queries = registration_work(tasks), queries_to_register(tasks)
        maps = self.count_maps(inputs, rankings, tasks, num_rankings)
        return ParadigmWork(self.label, query_pairs, *maps, *registrations, queries, shared_map=self.shared_map)

    def run(
        self, scene: Scene, rankings: Sequence[Ranking], sfm: SfmSettings, cache_dir: Path | None
    ) -> list[PoseEstimates] | None:
        estimates = run_sfm(sfm_inputs(scene, sfm, cache_dir, [self.label]), rankings, {self.label: self}).estimates
        return None if estimates is None else estimates[self.label]


def count_work(
    inputs: SfmInputs,
    rankings: Sequence[Ranking] | None,
    paradigms: Mapping[str, SfmParadigm],
    num_rankings: int = 0,
) -> SfmPlan:
    """The work of ``paradigms`` (`SfmPlan`), counted without doing any: exact for ``rankings``,
    upper bounds for ``num_rankings`` rankings not computed yet (``None``)."""
    work = [
        dataclasses.replace(paradigm.count(inputs, rankings, num_rankings), paradigm=name)
        for name, paradigm in paradigms.items()
    ]
    plan = SfmPlan(feature_work(inputs), work, rankings is not None)
    if rankings is not None:
        ks, deepest = ranked_ks(rankings, paradigms)
        query_pairs = inputs.ranked_pairs(rankings, deepest)
        database_pairs = [*shared_map_pairs(inputs, paradigms), *query_map_pairs(inputs, rankings, paradigms, ks)]
        plan.pairs_to_match = len(inputs.query_pairs.todo(query_pairs, inputs.query_verification)[0]) + len(
            inputs.database_pairs.todo(database_pairs, inputs.database_verification)[0]
        )
    return plan


def ranked_ks(
    rankings: Sequence[Ranking], paradigms: Mapping[str, SfmParadigm]
) -> tuple[dict[str, list[list[int]]], list[list[int]]]:
    """Each paradigm's ks per ranking (limited to its depth), and per ranking the deepest of them
    (each query's pairs to match: its top max(k) of every ranking)."""
    ks = {name: [ranking.clamp_ks(paradigm.k) for ranking in rankings] for name, paradigm in paradigms.items()}
    deepest = [[max(max(ks[name][r]) for name in paradigms)] for r in range(len(rankings))]
    return ks, deepest


def shared_map_pairs(inputs: SfmInputs, paradigms: Mapping[str, SfmParadigm]) -> list[Pair]:
    """The database pairs of every paradigm's maps that every query shares."""
    return [pair for paradigm in paradigms.values() for pair in paradigm.shared_map_pairs(inputs)]


def query_map_pairs(
    inputs: SfmInputs,
    rankings: Sequence[Ranking],
    paradigms: Mapping[str, SfmParadigm],
    ks: Mapping[str, list[list[int]]],
    queries: Sequence[int] | None = None,
) -> list[Pair]:
    """The database pairs of every paradigm's maps of ``queries`` (None: all), each with its ``ks``."""
    return [
        pair
        for name, paradigm in paradigms.items()
        for pair in paradigm.query_map_pairs(inputs, rankings, ks[name], queries)
    ]


def run_sfm(
    inputs: SfmInputs,
    rankings: Sequence[Ranking],
    paradigms: Mapping[str, SfmParadigm],
    shard: Shard | None = None,
    queries: Sequence[int] | None = None,
) -> SfmRun:
    """Every SfM paradigm of ``paradigms`` (by name) on every ranking; the pose estimates by
    paradigm, or None for a job of a ``shard`` or a run of some ``queries`` only (their share
    cached only).

    The work is counted first (`count_work`, logged). The queries are streamed in chunks
    (`stream_chunks`): while one chunk is triangulated and registered, the next chunk's pairs are
    matched. Each stage shows its progress and is timed where it runs (`StageMeter`); the records
    are logged."""
    started, scene = time.perf_counter(), inputs.scene
    plan = count_work(inputs, rankings, paradigms)
    log.log(logging.INFO if queries is None else logging.DEBUG, "%s", plan.describe())
    ks, deepest = ranked_ks(rankings, paradigms)
    chosen = list(range(len(scene.queries))) if queries is None else list(queries)
    chosen = chosen if shard is None else shard.take(chosen)
    shared_pairs = shared_map_pairs(inputs, paradigms)
    if shard is not None:  # every database pair of any map, split among the jobs
        shared_pairs = shard_database_pairs(
            inputs, shard, [*shared_pairs, *query_map_pairs(inputs, rankings, paradigms, ks)], len(chosen)
        )
    planned = plan.stage_units()
    if shard is not None or queries is not None:  # a share of the work: its bars count without a total
        planned = {stage: (None, unit) for stage, (_, unit) in planned.items()}
    meter = StageMeter(planned)
    with meter(FEATURES):
        extract_pair_features(
            inputs,
            shard,
            inputs.ranked_pairs(rankings, deepest, chosen),
            [*shared_pairs, *query_map_pairs(inputs, rankings, paradigms, ks, chosen)],
        )
    with meter(MATCHING):
        match_and_verify(inputs, [], shared_pairs)
    triangulate_shared_maps(inputs, paradigms, plan, meter)

    def match(chunk: Sequence[int]) -> None:
        with meter(MATCHING):
            match_and_verify(
                inputs,
                inputs.ranked_pairs(rankings, deepest, chunk),
                query_map_pairs(inputs, rankings, paradigms, ks, chunk),
            )

    def localize(chunk: Sequence[int]) -> None:
        for name, paradigm in paradigms.items():
            triangulate, register = stage_names(name)
            with meter(triangulate):
                paradigm.triangulate_query_maps(inputs, rankings, ks[name], chunk)
            with meter(register):
                paradigm.register(inputs, rankings, ks[name], chunk)

    stream_chunks(chosen, match, localize)
    estimates = None if shard is not None or queries is not None else gather(inputs, rankings, paradigms, ks, meter)
    stages, seconds = meter.close(), time.perf_counter() - started
    log.info("SfM in %.1f s: %s", seconds, "; ".join(f"{stage} {record}" for stage, record in stages.items()))
    return SfmRun(estimates, plan, stages, seconds)


def triangulate_shared_maps(
    inputs: SfmInputs, paradigms: Mapping[str, SfmParadigm], plan: SfmPlan, meter: StageMeter
) -> None:
    """Each paradigm's maps that every query shares, triangulated (or read) in this process before any
    query, their progress counted as the ``plan`` counted them."""
    for work, paradigm in zip(plan.paradigms, paradigms.values()):
        triangulate = stage_names(work.paradigm)[0]
        with meter(triangulate):
            paradigm.triangulate_shared_map(inputs)
        if work.shared_map and work.maps.new:
            meter.advance(triangulate, work.maps.new)


def gather(
    inputs: SfmInputs,
    rankings: Sequence[Ranking],
    paradigms: Mapping[str, SfmParadigm],
    ks: Mapping[str, list[list[int]]],
    meter: StageMeter,
) -> dict[str, list[PoseEstimates]]:
    """Every paradigm's estimates, their outcomes read from the cache (every query registered by then)."""
    estimates = {}
    for name, paradigm in paradigms.items():
        with meter(stage_names(name)[1]):
            estimates[name] = paradigm.register(inputs, rankings, ks[name], None)
    return estimates


def shard_database_pairs(inputs: SfmInputs, shard: Shard, pairs: Sequence[Pair], queries: int) -> list[Pair]:
    """The ``shard``'s share of the database ``pairs`` of every map (logged with its share of ``queries``)."""
    every = inputs.database_pairs.canonical(pairs)
    taken = shard.take(every)
    log.info(
        "SfM shard %s: %d of %d queries, %d of %d database pairs",
        shard,
        queries,
        len(inputs.scene.queries),
        len(taken),
        len(every),
    )
    return taken
