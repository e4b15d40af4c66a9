"""The work of the SfM paradigms, counted and forecast before any of it is done.

Per paradigm: the query-database pairs to match, the database pairs to match, the maps to
triangulate, the registrations and the queries they belong to, each as needed in all and new
(not in the caches); for the scene: the images whose local features are not cached. With the
rankings known the counts are exact; before (``evaluate.py dry_run=true``) they are upper
bounds: every ranking's top-k taken as disjoint from the others'.

The forecast multiplies the new work by unit costs measured on this machine just before, by
running the pipeline's own stages (`run_sfm`, into a temporary cache) on a sample of the scene
(`measure_unit_costs`: a neighbourhood of database images and a few queries ranking it), in one
process with one thread as a worker runs them, so that reading and writing the stores, the work
per map and per query are in the units; it then spreads each stage over the processes that
`run_sfm` will give it (`runs_here`, the worker pool started now when a stage will need it), and
adds each stage's cost per call (finding its new work in the stores, handing it out, writing
it) and, for the stages with a task per query, its cost per query (reading the query's matches
and its maps' images, once for all its maps), which the sample's runs with more and more queries,
then more rankings, tell apart from the cost per unit, and where the pool runs a stage, the cost
of a call of the pool (timed on the run's inputs).
It assumes the machine stays as loaded as it was when measured (the log gives that load).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import lsq_linear

from locretrieval.cache import temporary_folder
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene
from locretrieval.sfm.features import IMAGES_PER_SHARD
from locretrieval.sfm.inputs import QueryTask, SfmInputs, SfmSettings
from locretrieval.sfm.matching import PAIRS_PER_SHARD, pair_key
from locretrieval.sfm.pipeline import SfmStages, run_sfm, stage_names
from locretrieval.sfm.workers import (
    as_workers_load_it,
    parallel_map,
    runs_here,
    start_workers,
    task_size,
    workers_started,
)
from locretrieval.threads import single_threaded

log = logging.getLogger(__name__)

#: Seconds of a stage in one process above which the worker pool is started before the run.
POOL_WORTH_SECONDS = 10.0
#: Queries of the sample's runs, each run adding its new ones (`SAMPLE_RUNS`).
SAMPLE_QUERIES = 8
#: The sample's queries in each of its runs: the first with the database's work, then one more query
#: (its stages little more than their cost per call), then six more (new work: theirs alone), so that
#: each stage's units differ enough between the runs to tell its cost per call from its cost per unit
#: (`_stage_costs`). With three more, a run's stage of tens of milliseconds varied by 10 ms
#: between identical runs, as much as three queries' local maps added: units from 0.04 to 0.14 ms.
SAMPLE_RUNS = (1, 2, SAMPLE_QUERIES)
#: More rankings of the sample's last run: its queries ranked again in random orders of the
#: neighbourhood (`_more_rankings`), each query with as many more new maps, so that a query's cost in
#: its stages is told apart from its maps' (`_stage_costs`). With one ranking per query the sample
#: spread a query's reads over 2 maps, while the training validation's four reference rankings spread
#: them over 8: its local maps took 0.50-0.64 of their forecast, its local registrations 0.45-0.84.
#: Random orders, not rankings as good as the first: those left the registrations' unit at the best
#: maps' (PnP's LO-RANSAC takes longer on worse-ranked maps), `evaluate.py`'s took 1.46-1.59x.
SAMPLE_MORE_RANKINGS = 3
#: Database images of the sample (or the whole database when smaller), whatever the paradigms' k: a
#: map's fixed costs (a tenth of a second) over a sample of 10 images made the unit per map pair 3.5x
#: that of 1,487 pairs, over 50 images 0.8x (training validation, 300 keypoints, 2-core machine).
SAMPLE_DATABASE = 50
#: Queries whose registrations in the whole map every query shares are timed, when its inputs are cached.
MAP_SAMPLE_QUERIES = 6


@dataclass(frozen=True)
class Work:
    """``total`` items needed, ``new`` of them not cached."""

    total: int
    new: int

    def __str__(self) -> str:
        return f"{self.total:,} ({self.new:,} new)"


@dataclass
class ParadigmWork:
    """What one SfM paradigm needs: query-database and database pairs to match, maps to
    triangulate (with ``pairs_per_map`` matched pairs each, on average; ``parallel_maps``: each
    query's own, in the worker processes, else one map every query shares, in this process),
    registrations, the database images they register against (summed over them: their
    correspondences, so their cost, grow with it) and the ``queries`` they are of."""

    paradigm: str
    query_pairs: Work
    database_pairs: Work
    maps: Work
    pairs_per_map: float
    registrations: Work
    registered_images: Work
    queries: Work
    parallel_maps: bool = True

    @property
    def new_map_pairs(self) -> float:
        """Matched pairs to triangulate into new maps."""
        return self.maps.new * self.pairs_per_map

    @property
    def map_tasks(self) -> int:
        """Tasks of its triangulation: one per query with a new map (at most as many as new maps
        and as queries with a registration not cached), or the one map every query shares."""
        return min(self.maps.new, self.queries.new) if self.parallel_maps else min(self.maps.new, 1)


@dataclass(frozen=True)
class UnitCosts:
    """Seconds per unit of work in one process with one thread, as a worker process runs it,
    measured by `measure_unit_costs`: ``features`` per image, ``pairs`` per pair matched and
    verified (on ``device``), and per paradigm ``map_pairs`` per matched pair triangulated into
    a map and ``registrations`` per database image a query is registered against (reading its
    map and matches included).
    ``keypoints``: mean per image of the sample, ``sample``: what it was, ``load``: the
    machine's one-minute load average when measured, ``worker_start``: seconds the worker pool
    took to start for the run (0: none needed or already running); ``registrations_on_map``: the
    paradigms whose registration unit was timed on their whole map with the run's rankings
    (`registration_unit_on_map`), by name, with what it was measured on; ``per_call``: the seconds
    a stage with new work takes beyond its units, by stage name (`stage_names`): finding its new
    work in the stores, handing it out and writing it (a per-unit cost alone would spread it over
    the sample's few units); ``per_task``: the seconds of each task of the stages with one task
    per query (`SfmPlan.query_tasks`), beyond its units, by stage name: reading the query's
    matches and its maps' images once for all its maps; ``idle``: the seconds of a stage without
    new work (looking for it in the stores), by stage name; ``pool_call``: the seconds a call of the started worker pool
    takes beyond its tasks' work (`pool_call_seconds`, on the run's inputs; 0: no pool), which the
    sample, run in one process, never pays."""

    features: float
    pairs: float
    map_pairs: dict[str, float]
    registrations: dict[str, float]
    keypoints: float
    device: str
    sample: str
    load: float
    worker_start: float = 0.0
    registrations_on_map: dict[str, str] = field(default_factory=dict)
    per_call: dict[str, float] = field(default_factory=dict)
    per_task: dict[str, float] = field(default_factory=dict)
    idle: dict[str, float] = field(default_factory=dict)
    pool_call: float = 0.0


@dataclass
class SfmPlan:
    """The SfM work of a run: ``features`` (images of both sets), one `ParadigmWork` per
    paradigm, whether the counts are ``exact`` (or upper bounds), the worker ``processes``."""

    features: Work
    paradigms: list[ParadigmWork]
    exact: bool
    processes: int
    costs: UnitCosts | None = field(default=None)

    def new_query_pairs(self) -> int:
        """New query pairs: shared by the paradigms (each query with its top max(k) of every ranking)."""
        return max((p.query_pairs.new for p in self.paradigms), default=0)

    def new_pairs(self) -> int:
        """Pairs to match: new query pairs and new database pairs."""
        return self.new_query_pairs() + sum(p.database_pairs.new for p in self.paradigms)

    @property
    def has_new_work(self) -> bool:
        return bool(
            self.features.new or self.new_pairs() or any(p.maps.new or p.registrations.new for p in self.paradigms)
        )

    def pool_needed(self) -> bool:
        """Whether the worker pool is worth starting before the run (`costs` required): some stage
        would start it anyway (`runs_here`), or would take more than `POOL_WORTH_SECONDS` in one
        process while it can be split."""
        single = self.one_process_seconds()
        return any(
            tasks > 1 and (not runs_here(tasks, self.processes, started=False) or single[stage] > POOL_WORTH_SECONDS)
            for stage, tasks in self._tasks().items()
        )

    def _tasks(self) -> dict[str, int]:
        """The tasks of each stage, by its name (`stage_names`), in the order `run_sfm` runs
        them (as `split` cuts them): features, match + verify, the maps every query shares, then
        each paradigm's per-query triangulation and its registration."""
        pairs_cap = PAIRS_PER_SHARD if self.costs is None or self.costs.device == "cpu" else math.inf
        tasks = {
            "features": _task_count(self.features.new, IMAGES_PER_SHARD, self.processes),
            "match + verify": _task_count(self.new_pairs(), pairs_cap, self.processes),
        }
        tasks |= {stage_names(p.paradigm)[0]: p.map_tasks for p in self.paradigms if not p.parallel_maps}
        return tasks | self.query_tasks()

    def query_tasks(self) -> dict[str, int]:
        """The tasks of the stages with one task per query, by stage name, in the order `run_sfm`
        runs them: each paradigm's triangulation of its queries' own maps and its registration."""
        tasks = {}
        for p in self.paradigms:
            triangulate, register = stage_names(p.paradigm)
            tasks |= {triangulate: p.map_tasks} if p.parallel_maps else {}
            tasks[register] = p.queries.new
        return tasks

    def units(self) -> dict[str, float]:
        """The new units of each stage of `_tasks` (what `UnitCosts` are per): images, pairs, then
        per paradigm map pairs to triangulate and images registered against."""
        units = {"features": float(self.features.new), "match + verify": float(self.new_pairs())}
        for p in self.paradigms:
            triangulate, register = stage_names(p.paradigm)
            units[triangulate], units[register] = p.new_map_pairs, float(p.registered_images.new)
        return units

    def one_process_seconds(self) -> dict[str, float]:
        """Seconds of the units of each stage of `_tasks` in one process, and of its tasks where
        they have a cost of their own (`UnitCosts.per_task`; `costs` required)."""
        costs = self.costs
        assert costs is not None, "the stages' seconds need measured unit costs"
        per_unit = {"features": costs.features, "match + verify": costs.pairs}
        for p in self.paradigms:
            triangulate, register = stage_names(p.paradigm)
            per_unit[triangulate], per_unit[register] = costs.map_pairs[p.paradigm], costs.registrations[p.paradigm]
        tasks = self.query_tasks()
        return {
            stage: units * per_unit[stage] + tasks.get(stage, 0) * costs.per_task.get(stage, 0.0)
            for stage, units in self.units().items()
        }

    def forecast(self) -> dict[str, float]:
        """Seconds per stage for the new work (`costs` required), by the names `run_sfm` times
        its stages under: each stage's units and tasks in one process (`one_process_seconds`), spread over the
        worker processes `run_sfm` gives it (`runs_here`: a small workload stays in this process
        until the pool is started, and the pool then serves every later stage); matching on a
        CPU over every core either way (workers, or this process's threads), on a GPU in one
        process; a map every query shares in this process; plus the stage's cost per call
        (`UnitCosts.per_call`) where it has new work, and a call of the pool's (``pool_call``)
        where the pool runs it; a stage without new work its seconds looking for it
        (`UnitCosts.idle`). Ordered as `run_sfm` runs the stages."""
        costs = self.costs
        assert costs is not None, "forecast needs measured unit costs"
        started = workers_started(self.processes) or costs.worker_start > 0

        def spread(tasks: int) -> int:
            nonlocal started
            if tasks <= 1 or runs_here(tasks, self.processes, started):
                return 1
            started = True
            return min(self.processes, tasks)

        single = self.one_process_seconds()
        in_this_process = {stage_names(p.paradigm)[0] for p in self.paradigms if not p.parallel_maps}
        if costs.device != "cpu":  # one process matches on the device (the workers verify)
            in_this_process.add("match + verify")
        seconds = {}
        for stage, tasks in self._tasks().items():
            if not tasks:
                seconds[stage] = costs.idle.get(stage, 0.0)
                continue
            processes = 1 if stage in in_this_process else spread(tasks)
            seconds[stage] = single[stage] / processes + costs.per_call.get(stage, 0.0)
            seconds[stage] += costs.pool_call if processes > 1 else 0.0
        return seconds

    def describe(self) -> str:
        """The plan as log lines."""
        kind = "exact" if self.exact else "upper bounds: the rankings are not computed yet, each taken as disjoint"
        lines = [f"SfM plan ({kind}); local features of {self.features} images"]
        for p in self.paradigms:
            lines.append(
                f"  {p.paradigm}: query pairs {p.query_pairs}, database pairs {p.database_pairs}, "
                f"maps {p.maps} (~{p.pairs_per_map:,.0f} pairs each), registrations {p.registrations}"
            )
        if self.costs is not None:
            c = self.costs
            units = ", ".join(
                f"{name} {c.map_pairs[name] * 1e3:.2f} ms/map pair and "
                f"{c.registrations[name] * 1e3:.2f} ms/registered image"
                + (f" (timed on {c.registrations_on_map[name]})" if name in c.registrations_on_map else "")
                for name in c.map_pairs
            )
            per_call = ", ".join(f"{stage} {seconds * 1e3:.0f} ms" for stage, seconds in c.per_call.items())
            per_task = ", ".join(f"{stage} {seconds * 1e3:.1f} ms" for stage, seconds in c.per_task.items())
            lines.append(
                f"  unit costs measured just now by running the pipeline on {c.sample} of the scene "
                f"({c.keypoints:.0f} keypoints per image, matching on {c.device}), in one process with one thread, "
                f"while the machine's load average was {c.load:.1f}: features {c.features:.3f} s/image, "
                f"match + verify {c.pairs * 1e3:.1f} ms/pair, {units}"
                + (f"; per stage call with new work: {per_call}" if per_call else "")
                + (f"; per query: {per_task}" if per_task else "")
                + f"; spread over {self.processes} worker "
                f"process(es){f' (their pool started in {c.worker_start:.1f} s)' if c.worker_start else ''}"
                f"{f', {c.pool_call * 1e3:.0f} ms per call of their pool' if c.pool_call else ''}; "
                "a machine busier than when measured takes longer"
            )
            stages = self.forecast()
            lines.append(
                "  forecast: "
                + ", ".join(f"{stage} {_duration(seconds)}" for stage, seconds in stages.items())
                + f"; total {_duration(sum(stages.values()))}"
                + ("" if self.exact else " at most")
            )
        return "\n".join(lines)


def prepare_workers(plan: SfmPlan, inputs: SfmInputs) -> SfmPlan:
    """``plan`` with the worker pool started now when it is worth it (`SfmPlan.pool_needed`), the
    seconds that took in its costs, and those of a call of the pool on the run's ``inputs``
    (`pool_call_seconds`) when the run will use it."""
    if plan.costs is None:
        return plan
    if not workers_started(plan.processes) and plan.pool_needed():
        plan.costs = dataclasses.replace(plan.costs, worker_start=start_workers(plan.processes))
    if workers_started(plan.processes):
        plan.costs = dataclasses.replace(plan.costs, pool_call=pool_call_seconds(inputs, plan.processes))
    return plan


def pool_call_seconds(inputs: SfmInputs, workers: int) -> float:
    """Seconds a call of the started pool of ``workers`` takes beyond its tasks' work, timed with
    the run's ``inputs`` as every stage hands them out: pickled once, loaded by each worker (the
    stores' indexes with them, their in-memory shards empty: `ShardedStore.__getstate__`), the
    answers gathered. The tasks' own reads are in their units already, so the probe reads nothing;
    one load of the inputs is in the sample's cost per call too (`as_workers_load_it`): a few
    milliseconds counted twice, left in rather than timed apart."""
    started = time.perf_counter()
    for _ in parallel_map(_database_size, range(workers), workers, "forecast: a pool call", inputs):
        pass
    return time.perf_counter() - started


def _database_size(inputs: SfmInputs, task: int) -> int:
    """A task of a pool call that only loads the call's ``inputs``."""
    return len(inputs.scene.database)


def _task_count(items: int, cap: float, workers: int) -> int:
    """Tasks `split` cuts ``items`` into."""
    return math.ceil(items / task_size(items, cap, workers)) if items else 0


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.1f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def feature_work(inputs: SfmInputs) -> Work:
    """Images of both sets, and those whose features are not cached."""
    scene = inputs.scene
    new = len(inputs.database_features.store.missing(scene.database.names)) + len(
        inputs.query_features.store.missing(scene.queries.names)
    )
    return Work(len(scene.database) + len(scene.queries), new)


def query_pair_work(
    inputs: SfmInputs, rankings: Sequence[Ranking] | None, ks: Sequence[int], num_rankings: int
) -> Work:
    """Query-database pairs of every query's top ``max(ks)`` of each ranking (``None``: upper
    bounds for ``num_rankings`` rankings), and those not matched yet."""
    scene = inputs.scene
    if rankings is None:
        bound = min(
            num_rankings * len(scene.queries) * min(max(ks), len(scene.database)),
            len(scene.queries) * len(scene.database),
        )
        return Work(bound, bound)
    pairs = inputs.query_pairs.canonical(inputs.ranked_pairs(rankings, [r.clamp_ks(ks) for r in rankings]))
    return Work(len(pairs), len(inputs.query_pairs.raw.missing(map(pair_key, pairs))))


def database_pair_work(inputs: SfmInputs, pairs: Iterable[tuple[str, str]]) -> Work:
    """Database pairs (names), and those not matched yet."""
    pairs = inputs.database_pairs.canonical(pairs)
    return Work(len(pairs), len(inputs.database_pairs.raw.missing(map(pair_key, pairs))))


def registration_work(tasks: Sequence[QueryTask]) -> tuple[Work, Work]:
    """Registrations (a query in one set of images) of ``tasks``, and those not cached; and the
    same summed over the images of each set."""
    return (
        Work(sum(len(task.image_sets()) for task in tasks), sum(len(task.pending()) for task in tasks)),
        Work(
            sum(len(images) for task in tasks for images in task.image_sets()),
            sum(len(images) for task in tasks for images in task.pending()),
        ),
    )


def registration_bound(queries: int, database: int, ks: Sequence[int], num_rankings: int) -> tuple[Work, Work]:
    """`registration_work` at most, for ``num_rankings`` rankings not computed yet."""
    registrations = num_rankings * queries * len(ks)
    images = num_rankings * queries * sum(min(k, database) for k in ks)
    return Work(registrations, registrations), Work(images, images)


def queries_to_register(tasks: Sequence[QueryTask]) -> Work:
    """Queries of ``tasks``, and those with a registration not cached (a task of the per-query stage)."""
    return Work(len(tasks), sum(not task.complete for task in tasks))


def forecast_sample(scene: Scene, depth: int, queries: int = SAMPLE_QUERIES) -> tuple[Scene, Ranking]:
    """A neighbourhood of ``scene`` to measure unit costs on, and its ranking: the ``depth``
    database images nearest (camera centres) to the one nearest the database's centroid, and
    the ``queries`` queries nearest to that one (the first ones where queries have no reference
    pose), each ranking the neighbourhood by distance to itself (to that one, without a pose)."""
    database, all_queries = scene.database, scene.queries
    centres = database.centers
    seed = int(np.argmin(np.linalg.norm(centres - centres.mean(0), axis=1)))
    neighbours = np.argsort(np.linalg.norm(centres - centres[seed], axis=1), kind="stable")[:depth]
    posed = np.flatnonzero(all_queries.has_pose)
    if len(posed):
        chosen = posed[np.argsort(np.linalg.norm(all_queries.centers[posed] - centres[seed], axis=1), kind="stable")]
    else:
        chosen = np.arange(len(all_queries))
    chosen = chosen[:queries]
    anchors = np.where(all_queries.has_pose[chosen, None], all_queries.centers[chosen], centres[seed])
    distances = np.linalg.norm(anchors[:, None] - centres[neighbours][None], axis=2)
    order = np.argsort(distances, axis=1, kind="stable")
    ranking = Ranking("forecast sample", order, -np.take_along_axis(distances, order, axis=1), "groundtruth")
    sample = Scene(
        f"{scene.name} (forecast sample)",
        database.subset(neighbours),
        all_queries.subset(chosen),
        frustum_far=scene.frustum_far,
    )
    return sample, ranking


def sample_depth(scene: Scene) -> int:
    """Database images of `measure_unit_costs`' sample: `SAMPLE_DATABASE`, or the whole database."""
    return min(len(scene.database), SAMPLE_DATABASE)


def measure_unit_costs(
    scene: Scene,
    settings: SfmSettings,
    paradigms: Mapping[str, SfmStages],
    cache_dir: Path,
    rankings: Sequence[Ranking] | None = None,
) -> UnitCosts:
    """Unit costs of the SfM stages, measured by `run_sfm` itself on `forecast_sample` (a
    neighbourhood of `SAMPLE_DATABASE` database images ranked by `SAMPLE_QUERIES` queries)
    with the run's paradigms, in one process with one thread, each stage's call starting from its
    inputs loaded afresh as a worker's does (`as_workers_load_it`), into a temporary folder of
    ``cache_dir`` (deleted afterwards): runs with the first queries (`SAMPLE_RUNS`), each adding
    new ones, then one with `SAMPLE_MORE_RANKINGS` more rankings of them (`_more_rankings`),
    each stage's seconds (the pipeline's own stage clock), new tasks and new units (their
    `SfmPlan`) in every run split into a cost per call, per task and per unit (`_stage_costs`);
    the mean seconds of its runs without new work are its seconds looking for work (``idle``).
    With the run's ``rankings``, a paradigm's registrations in a map every query shares are
    timed on that map instead, where it is cheap to build
    (`registration_unit_on_map`: it does some of the run's own work, in ``cache_dir``)."""
    sample, ranking = forecast_sample(scene, sample_depth(scene))
    parts = [
        (
            dataclasses.replace(sample, queries=sample.queries.subset(np.arange(queries))),
            [Ranking(ranking.name, ranking.indices[:queries], ranking.scores[:queries], ranking.kind)],
        )
        for queries in sorted({min(queries, len(sample.queries)) for queries in SAMPLE_RUNS})
    ]
    parts.append((sample, [ranking, *_more_rankings(ranking, SAMPLE_MORE_RANKINGS)]))
    one_process = dataclasses.replace(settings, workers=1)
    load = os.getloadavg()[0]
    with temporary_folder(cache_dir, "forecast") as folder, single_threaded(), as_workers_load_it(), _quiet():
        runs = [_timed_run(part, part_rankings, paradigms, one_process, folder) for part, part_rankings in parts]
        inputs = SfmInputs.prepare(sample, one_process, folder, extract=False)
        keypoints = inputs.database_features.keypoints(sample.database.names)
    per_call, per_task, per_unit, idle = {}, {}, {}, {}
    for stage in runs[0]:
        per_call[stage], per_task[stage], per_unit[stage] = _stage_costs([run[stage] for run in runs])
        idle[stage] = float(
            np.mean([seconds for _, units, seconds in (run[stage] for run in runs) if not units] or [0.0])
        )
    map_pairs, registrations = {}, {}
    for name in paradigms:
        triangulate, register = stage_names(name)
        map_pairs[name], registrations[name] = per_unit[triangulate], per_unit[register]
    on_map = {}
    for name, stages in paradigms.items():
        register = stage_names(name)[1]
        measured = (
            None
            if rankings is None
            else registration_unit_on_map(scene, one_process, stages, cache_dir, rankings, per_call[register])
        )
        if measured is not None:
            registrations[name], on_map[name] = measured
    return UnitCosts(
        per_unit["features"],
        per_unit["match + verify"],
        map_pairs,
        registrations,
        float(np.mean([len(points) for points in keypoints.values()])),
        settings.matching.matcher().device,
        f"{len(sample.database)} database images and {' then '.join(str(len(part.queries)) for part, _ in parts[:-1])} "
        f"of its queries, then those by {len(parts[-1][1]) - 1} more rankings",
        load,
        registrations_on_map=on_map,
        per_call={stage: seconds for stage, seconds in per_call.items() if seconds},
        per_task={stage: seconds for stage, seconds in per_task.items() if seconds},
        idle={stage: seconds for stage, seconds in idle.items() if seconds},
    )


def _more_rankings(ranking: Ranking, count: int) -> list[Ranking]:
    """``count`` rankings of ``ranking``'s queries, each a random order of its images (seeded):
    other maps for each query, of lower quality, as a run's rankings give it."""
    generator = np.random.default_rng(0)
    return [
        Ranking(
            f"{ranking.name}, shuffled {number}",
            generator.permuted(ranking.indices, axis=1),
            ranking.scores,
            "baseline",
        )
        for number in range(1, count + 1)
    ]


def _timed_run(
    scene: Scene, rankings: Sequence[Ranking], paradigms: Mapping[str, SfmStages], settings: SfmSettings, folder: Path
) -> dict[str, tuple[float, float, float]]:
    """Per stage of `run_sfm` on ``scene`` into ``folder``: its new tasks where it has one per query
    (`SfmPlan.query_tasks`, else 0), its new units (`SfmPlan.units`), both counted before, and the
    seconds it took."""
    inputs = SfmInputs.prepare(scene, settings, folder, extract=False)
    work = [stages.plan(scene, rankings, settings, folder, 0) for stages in paradigms.values()]
    work = [dataclasses.replace(w, paradigm=name) for w, name in zip(work, paradigms)]
    plan = SfmPlan(feature_work(inputs), work, True, 1)
    units, tasks = plan.units(), plan.query_tasks()
    seconds: dict[str, float] = {}
    run_sfm(scene, rankings, paradigms, settings, folder, seconds)
    return {stage: (tasks.get(stage, 0), count, seconds.get(stage, 0.0)) for stage, count in units.items()}


def _stage_costs(runs: Sequence[tuple[float, float, float]]) -> tuple[float, float, float]:
    """A stage's seconds per call (with new work), per task and per unit from the sample's runs'
    (new tasks, new units, seconds): the least-squares plane through the runs with new units in
    relative terms (each run's residual over its seconds: the forecast is judged by its ratio to
    the time taken, and the sample's largest run would otherwise fit the small ones badly), all
    three at least 0 and the cost per call at most the shortest run's seconds (scipy's bounded
    least squares); without tasks, or with fewer distinct runs than costs, the line through them
    without a cost per task, then without a cost per call (a run without new units only looked
    for work: left out)."""
    with_units = np.array([run for run in runs if run[1]], dtype=float).reshape(-1, 3)
    if not len(with_units):
        return 0.0, 0.0, 0.0
    tasks, units, seconds = with_units.T
    columns = np.column_stack([np.ones_like(units), tasks, units])
    for kept in ([0, 1, 2], [0, 2], [2]):
        scale = np.abs(columns[:, kept]).max(axis=0)
        scaled = columns[:, kept] / np.where(scale > 0, scale, 1.0)
        if np.linalg.matrix_rank(scaled, tol=1e-6) == len(kept):
            break
    upper = np.array([seconds.min(), np.inf, np.inf])[kept]
    fitted = np.zeros(3)
    weights = 1.0 / np.maximum(seconds, 1e-6)[:, None]
    fitted[kept] = lsq_linear(columns[:, kept] * weights, np.ones_like(seconds), bounds=(np.zeros(len(kept)), upper)).x
    per_call, per_task, per_unit = (float(value) for value in fitted)
    return per_call, per_task, per_unit


def registration_unit_on_map(
    scene: Scene,
    settings: SfmSettings,
    stages: SfmStages,
    cache_dir: Path,
    rankings: Sequence[Ranking],
    per_call: float = 0.0,
) -> tuple[float, str] | None:
    """Seconds per registered image of ``stages``' registrations in the map every query shares
    (its `ParadigmWork` without ``parallel_maps``), timed on that map with the run's ``rankings``
    for `MAP_SAMPLE_QUERIES` queries spread over the scene, in one process with one thread, less
    the stage's seconds ``per_call``, with what it was measured on; None when the paradigm has
    no such map, when the map would need features or matches that are not cached (a cold run),
    or when nothing is left after that: the sample's unit stands. The sample's cost per query
    is not subtracted: on the test scene's small map, six queries' registrations took less than
    it and the cost per call together, no unit left; the unit keeps it (a few milliseconds per
    query counted twice in the forecast).

    PnP's LO-RANSAC runs until its inliers are likely found, so its time per correspondence grows
    as the inlier ratio falls: a neighbourhood's map ranked by distance gave half the run's time per
    image (docs/performance.md). What it does is the run's own work, in the run's cache: the map
    (from cached features and matches), those queries' matches and registrations, none of which the
    run then does again (count the plan after it)."""
    work = stages.plan(scene, rankings, settings, cache_dir, 0)
    if work.parallel_maps or work.database_pairs.new or not work.registered_images.new:
        return None
    inputs = SfmInputs.prepare(scene, settings, cache_dir, extract=False)
    queries = np.unique(np.linspace(0, len(scene.queries) - 1, MAP_SAMPLE_QUERIES).round().astype(int)).tolist()
    if inputs.database_features.store.missing(scene.database.names) or inputs.query_features.store.missing(
        [scene.queries.names[q] for q in queries]
    ):
        return None
    ks = [ranking.clamp_ks(stages.k) for ranking in rankings]
    with single_threaded(), _quiet():
        inputs.query_pairs.ensure(sorted(inputs.ranked_pairs(rankings, ks, queries)), 1, inputs.query_verification)
        stages.triangulate_shared_map(inputs, cache_dir)
        with as_workers_load_it():  # as the sample timed the costs per call and per query subtracted
            started = time.perf_counter()
            stages.register(inputs, rankings, ks, cache_dir, queries)
            seconds = time.perf_counter() - started
    registered = work.registered_images.new - stages.plan(scene, rankings, settings, cache_dir, 0).registered_images.new
    if not registered:
        return None
    left = seconds - per_call
    if left <= 0:  # within the sample's noise: no unit measured, the sample's stands
        return None
    return left / registered, f"{len(queries)} queries and the run's rankings ({len(rankings)}) on the whole map"


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """The pipeline's and the paradigms' log below warnings while they run on a sample (its lines are not the run's)."""
    loggers = [logging.getLogger(name) for name in ("locretrieval.sfm", "locretrieval.paradigms")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)
