"""The SfM paradigms as one pipeline of explicit stages, driven once for every enabled SfM paradigm.

The stages hand each other their results through the caches:

1. **features**: local features of both image sets (`extract_features`, ``sfm.features``);
2. **match + verify** (`PairMatcher.ensure`: CPU workers, or the GPU fed by them): the database
   pairs of the maps every query shares (the global map), then, per chunk of queries, each
   query with its top ``max(k)`` images of every ranking (verified per
   ``sfm.query_verification``) and the database pairs of its local maps (pose-verified);
3. **triangulate** (``<paradigm>: triangulate``): the maps every query shares (the global map,
   `SfmStages.triangulate_shared_map`) once, in this process, before any query; the maps of each
   query (local maps, `SfmStages.triangulate_query_maps`) per chunk, in worker processes; both
   cached;
4. **register** (``<paradigm>: register``, `SfmStages.register`): each query of a chunk in its
   maps, in worker processes, outcomes cached.

`run_sfm` is the driver: it streams the queries in chunks, so that while one chunk is
triangulated and registered the next one is matched (on a GPU the two stages then overlap), and
gathers every outcome from the cache at the end. The paradigms say what they need
(`SfmStages`) and never match anything themselves, so one evaluation matches each pair once.

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
import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from locretrieval.estimates import PoseEstimates
from locretrieval.pool import cpu_time, progress_to
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene
from locretrieval.sfm.features import extract_features
from locretrieval.sfm.inputs import SfmInputs, SfmSettings
from locretrieval.sfm.work import FEATURES, MATCHING, ParadigmWork, SfmPlan, feature_work, stage_names
from locretrieval.shard import Shard

log = logging.getLogger(__name__)

Pair = tuple[str, str]
#: Queries per chunk of the streamed stages (a chunk is triangulated and registered while the next is matched).
QUERIES_PER_CHUNK = 512


class SfmStages(abc.ABC):
    """What an SfM paradigm adds to the pipeline: a `locretrieval.paradigms.SfmParadigm`
    implements these with its settings (``k`` among them):

    - `shared_map_pairs`: the database pairs of maps every query uses (the global map), to be
      matched and pose-verified;
    - `query_map_pairs`: those of maps built per query;
    - the stage ``<paradigm>: triangulate``: `triangulate_shared_map` triangulates (and caches)
      the maps every query uses, in this process, once their pairs are matched and before any
      query; `triangulate_query_maps` those of each query of a chunk, in worker processes (each
      a no-op for a paradigm without such maps);
    - the stage ``<paradigm>: register``: `register` registers each query of a chunk in its
      maps (in worker processes), outcomes cached, and gathers them at the end;
    - `count`: its work, counted without doing any (`locretrieval.sfm.work`).
    """

    #: The numbers of top-ranked images the paradigm localizes from (its settings').
    k: list[int]

    def shared_map_pairs(self, inputs: SfmInputs) -> list[Pair]:
        """The database pairs of the maps every query uses (default: none)."""
        return []

    def query_map_pairs(
        self, inputs: SfmInputs, rankings: Sequence[Ranking], ks: list[list[int]], queries: Sequence[int] | None
    ) -> list[Pair]:
        """The database pairs of the maps built per query, for ``queries`` (None: all; default: none)."""
        return []

    def triangulate_shared_map(self, inputs: SfmInputs, cache_dir: Path) -> None:
        """Triangulate (and cache) the maps every query uses (default: there are none)."""

    def triangulate_query_maps(
        self,
        inputs: SfmInputs,
        rankings: Sequence[Ranking],
        ks: Sequence[list[int]],
        cache_dir: Path,
        queries: Sequence[int],
    ) -> None:
        """Triangulate (and cache) the maps of each of ``queries`` whose registrations are not
        cached (default: there are none)."""

    @abc.abstractmethod
    def register(
        self,
        inputs: SfmInputs,
        rankings: Sequence[Ranking],
        ks: Sequence[list[int]],
        cache_dir: Path,
        queries: Sequence[int] | None,
    ) -> list[PoseEstimates] | None:
        """With ``queries`` (a chunk, or a shard's), register those in their maps (triangulated
        by then) and cache the outcomes only, returning None; with None, gather every outcome
        (cached by then) as estimates."""

    @abc.abstractmethod
    def count(self, inputs: SfmInputs, rankings: Sequence[Ranking] | None, num_rankings: int) -> ParadigmWork:
        """Its work (`ParadigmWork`), without doing any: exact for ``rankings``, upper bounds for
        ``num_rankings`` rankings not computed yet (``None``)."""


def sfm_inputs(scene: Scene, sfm: SfmSettings, cache_dir: str | Path | None, paradigms: Iterable[str]) -> SfmInputs:
    """The caches the SfM ``paradigms`` of a run share (`SfmInputs`), named once for the run."""
    if cache_dir is None:
        raise ValueError(f"{' and '.join(paradigms)} need a cache directory for their features, matches and maps")
    return SfmInputs.prepare(scene, sfm, Path(cache_dir), extract=False)


def count_work(
    inputs: SfmInputs,
    rankings: Sequence[Ranking] | None,
    paradigms: Mapping[str, SfmStages],
    num_rankings: int = 0,
) -> SfmPlan:
    """The work of ``paradigms`` (`SfmPlan`), counted without doing any: exact for ``rankings``,
    upper bounds for ``num_rankings`` rankings not computed yet (``None``)."""
    work = [
        dataclasses.replace(stages.count(inputs, rankings, num_rankings), paradigm=name)
        for name, stages in paradigms.items()
    ]
    plan = SfmPlan(feature_work(inputs), work, rankings is not None)
    if rankings is not None:
        ks, deepest = ranked_ks(rankings, paradigms)
        query_pairs = inputs.ranked_pairs(rankings, deepest)
        database_pairs = [
            *(pair for stages in paradigms.values() for pair in stages.shared_map_pairs(inputs)),
            *(
                pair
                for name, stages in paradigms.items()
                for pair in stages.query_map_pairs(inputs, rankings, ks[name], None)
            ),
        ]
        plan.pairs_to_match = len(inputs.query_pairs.todo(query_pairs, inputs.query_verification)[0]) + len(
            inputs.database_pairs.todo(database_pairs, inputs.database_verification)[0]
        )
    return plan


def ranked_ks(
    rankings: Sequence[Ranking], paradigms: Mapping[str, SfmStages]
) -> tuple[dict[str, list[list[int]]], list[list[int]]]:
    """Each paradigm's ks per ranking (limited to its depth), and per ranking the deepest of them
    (each query's pairs to match: its top max(k) of every ranking)."""
    ks = {name: [ranking.clamp_ks(stages.k) for ranking in rankings] for name, stages in paradigms.items()}
    deepest = [[max(max(ks[name][r]) for name in paradigms)] for r in range(len(rankings))]
    return ks, deepest


@dataclass
class StageRecord:
    """What a stage did in a run: its ``seconds`` of work (summed over its calls; stages overlap,
    so a run's records may add up to more than its time), its ``cpu_seconds`` (this process's while
    it ran and its tasks' in the worker processes, `cpu_time`; overlapping stages share this
    process's) and its ``done`` work in its ``unit``."""

    seconds: float = 0.0
    done: int = 0
    unit: str = ""
    cpu_seconds: float = 0.0

    def __str__(self) -> str:
        rate = f", {self.done / self.seconds:,.1f}/s" if self.done and self.seconds > 0 else ""
        return f"{self.done:,} {self.unit} in {self.seconds:.1f} s{rate}"


class StageMeter:
    """Times each stage where it runs and shows its progress in its own units: ``with meter(stage):
    ...`` (from several threads) adds the block's seconds and CPU seconds to the stage's record, and the tasks its
    worker pools finish to the stage's bar (tqdm: rate and time left from the stage's throughput so
    far) of the ``planned`` work (stage -> (units, unit name), `SfmPlan.stage_units`)."""

    def __init__(self, planned: Mapping[str, tuple[int | None, str]]) -> None:
        self.planned = dict(planned)
        self.records = {stage: StageRecord(unit=unit) for stage, (_, unit) in self.planned.items()}
        self._bars: dict[str, Any] = {}
        self._lock = threading.Lock()

    def advance(self, stage: str, units: int) -> None:
        """Count ``units`` of ``stage``'s work done (e.g. a map built in this process)."""
        with self._lock:
            record = self.records.setdefault(stage, StageRecord())
            record.done += units
            if stage not in self._bars:
                total, unit = self.planned.get(stage, (None, "tasks"))
                self._bars[stage] = tqdm(total=total, desc=stage, unit=f" {unit}", disable=None, leave=False)
            self._bars[stage].update(units)

    @contextlib.contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        started = time.perf_counter()
        try:
            with cpu_time() as cpu, progress_to(lambda units: self.advance(stage, units)):
                yield
        finally:
            with self._lock:
                record = self.records.setdefault(stage, StageRecord())
                record.seconds += time.perf_counter() - started
                record.cpu_seconds += cpu.seconds

    def close(self) -> dict[str, StageRecord]:
        """Close the bars; every stage's record."""
        for bar in self._bars.values():
            bar.close()
        return self.records


@dataclass
class SfmRun:
    """What `run_sfm` returns: the pose ``estimates`` by paradigm (None for a share of the queries),
    the ``plan`` it counted first, each stage's `StageRecord` and the run's ``seconds`` (wall clock)."""

    estimates: dict[str, list[PoseEstimates]] | None
    plan: SfmPlan
    stages: dict[str, StageRecord]
    seconds: float


def run_sfm(
    inputs: SfmInputs,
    rankings: Sequence[Ranking],
    paradigms: Mapping[str, SfmStages],
    shard: Shard | None = None,
    queries: Sequence[int] | None = None,
) -> SfmRun:
    """Every SfM paradigm of ``paradigms`` (name -> its `SfmStages`) on every ranking; the pose
    estimates by paradigm, or None for a job of a ``shard`` or a run of some ``queries`` only
    (their share cached only).

    The work is counted first (`count_work`, logged). The queries are streamed in chunks of
    `QUERIES_PER_CHUNK`: while one chunk is triangulated and registered (a thread driving the
    worker processes), the next chunk's pairs are matched (on the GPU, or the workers). Each
    stage shows its progress and is timed where it runs (`StageMeter`); the records are logged."""
    started, scene, cache_dir = time.perf_counter(), inputs.scene, inputs.cache_dir
    plan = count_work(inputs, rankings, paradigms)
    log.log(logging.INFO if queries is None else logging.DEBUG, "%s", plan.describe())
    ks, deepest = ranked_ks(rankings, paradigms)
    chosen = list(range(len(scene.queries))) if queries is None else list(queries)
    chosen = chosen if shard is None else shard.take(chosen)

    def query_map_pairs(chunk: Sequence[int] | None) -> list[Pair]:
        return [
            pair
            for name, stages in paradigms.items()
            for pair in stages.query_map_pairs(inputs, rankings, ks[name], chunk)
        ]

    shared_pairs = [pair for stages in paradigms.values() for pair in stages.shared_map_pairs(inputs)]
    if shard is not None:  # every database pair of any map, split among the jobs
        all_pairs = inputs.database_pairs.canonical([*shared_pairs, *query_map_pairs(None)])
        log.info(
            "SfM shard %s: %d of %d queries, %d of %d database pairs",
            shard,
            len(chosen),
            len(scene.queries),
            len(shard.take(all_pairs)),
            len(all_pairs),
        )
        shared_pairs = shard.take(all_pairs)
    planned = plan.stage_units()
    if shard is not None or queries is not None:  # a share of the work: its bars count without a total
        planned = {stage: (None, unit) for stage, (_, unit) in planned.items()}
    meter = StageMeter(planned)
    with meter(FEATURES):
        extract_stage(
            inputs,
            cache_dir,
            shard,
            inputs.ranked_pairs(rankings, deepest, chosen),
            [*shared_pairs, *query_map_pairs(chosen)],
        )
    with meter(MATCHING):
        match_stage(inputs, [], shared_pairs)
    for work, (name, stages) in zip(plan.paradigms, paradigms.items()):
        with meter(stage_names(name)[0]):
            stages.triangulate_shared_map(inputs, cache_dir)
        if work.shared_map and work.maps.new:
            meter.advance(stage_names(name)[0], work.maps.new)

    def localize(chunk: Sequence[int]) -> None:
        for name, stages in paradigms.items():
            triangulate, register = stage_names(name)
            with meter(triangulate):
                stages.triangulate_query_maps(inputs, rankings, ks[name], cache_dir, chunk)
            with meter(register):
                stages.register(inputs, rankings, ks[name], cache_dir, chunk)

    def gather() -> dict[str, list[PoseEstimates]]:
        found = {}
        for name, stages in paradigms.items():
            with meter(stage_names(name)[1]):
                found[name] = stages.register(inputs, rankings, ks[name], cache_dir, None)
        return found

    with ThreadPoolExecutor(1, thread_name_prefix="sfm-localize") as background:
        localizing = None
        for start in range(0, len(chosen), QUERIES_PER_CHUNK):
            chunk = chosen[start : start + QUERIES_PER_CHUNK]
            with meter(MATCHING):
                match_stage(inputs, inputs.ranked_pairs(rankings, deepest, chunk), query_map_pairs(chunk))
            if localizing is not None:
                localizing.result()  # one chunk localised at a time: the worker processes are its
            localizing = background.submit(localize, chunk)
        if localizing is not None:
            localizing.result()
    estimates = None if shard is not None or queries is not None else gather()  # every outcome is cached now
    stages, seconds = meter.close(), time.perf_counter() - started
    log.info("SfM in %.1f s: %s", seconds, "; ".join(f"{stage} {record}" for stage, record in stages.items()))
    return SfmRun(estimates, plan, stages, seconds)


def extract_stage(
    inputs: SfmInputs,
    cache_dir: Path,
    shard: Shard | None,
    query_pairs: Sequence[Pair],
    database_pairs: Sequence[Pair],
    whole_sets: bool = True,
) -> None:
    """Local features of every image of both sets (``whole_sets``; a shard's share of each), then
    of the images of the (query, database) and (database, database) pairs still missing."""
    scene, settings, workers = inputs.scene, inputs.settings, inputs.settings.processes
    needed = (
        (
            scene.database,
            sorted({name for _, name in query_pairs} | {name for pair in database_pairs for name in pair}),
        ),
        (scene.queries, sorted({query for query, _ in query_pairs})),
    )
    for images, names in needed:
        if whole_sets:
            extract_features(
                images, settings.features, cache_dir, workers, None if shard is None else shard.take(images.names)
            )
        extract_features(images, settings.features, cache_dir, workers, names)
    for store in (inputs.database_features, inputs.query_features):
        store.store.refresh()  # the run's stores, counted before: their indexes now hold the new features


def match_stage(inputs: SfmInputs, query_pairs: Sequence[Pair], database_pairs: Sequence[Pair]) -> None:
    """Match and verify every query pair and every database pair (each store in one pass)."""
    workers = inputs.settings.processes
    inputs.query_pairs.ensure(query_pairs, workers, inputs.query_verification)
    inputs.database_pairs.ensure(database_pairs, workers, inputs.database_verification)
