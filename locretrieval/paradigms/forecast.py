"""The forecast of a dry run (``evaluate.py dry_run=true``): what the SfM work will take here.

No run imports this module: a run measures its stages where they run (`StageMeter`). A dry run
counts the work before the rankings it cannot read from the caches are computed (`count_work`:
exact for the rankings given, cached work as cached; upper bounds for the others, each ranking's
top-k taken as disjoint, less the pairs the ground truth matches first: `counted_plan`), then
multiplies by unit costs measured on this machine (`calibrate`: the pipeline on a small
neighbourhood of the scene, in one process with one thread, into a temporary folder; then again
over its own cached work, for what reading work back costs): features per image, matching per
pair, triangulation per matched pair in a map, registration per database image a query is
registered against, each spread over the worker processes, and per unit of cached work what
reading it back costs. The unit costs are kept in the cache (`stored_calibration`: keyed by the
settings, the sample and the machine), so that two dry runs of one config forecast the same. A
machine busier than when calibrated takes longer; the forecast claims the measured run within
`BAND` of it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import platform
import statistics
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from math import comb
from pathlib import Path
from typing import Any

import numpy as np

from locretrieval.cache import config_key, load_arrays, save_arrays, temporary_folder
from locretrieval.paradigms.sfm import SfmParadigm, count_work, run_sfm
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.matching import pair_key
from locretrieval.sfm.settings import SfmSettings
from locretrieval.sfm.work import FEATURES, MATCHING, ParadigmWork, SfmPlan, Work, stage_names
from locretrieval.threads import single_threaded

log = logging.getLogger(__name__)

#: The measured run's SfM seconds are claimed within these factors of the forecast.
BAND = (0.5, 2.0)
#: Database images and queries of the calibration's neighbourhood: a few seconds of work.
CALIBRATION_DATABASE = 12
CALIBRATION_QUERIES = 3
#: The ground truth's own matching and joint map, forecast as stages of their own.
GROUNDTRUTH_MATCHING, GROUNDTRUTH_MAP = "ground truth: match + verify", "ground truth: triangulate"
#: A run's SfM work besides its stages' (counting the work, gathering the outcomes): the forecast's
#: entry, and its cost per registration in `Calibration.cached`.
CACHED_OTHER = "counting + gathering"
#: Passes over the calibration's own cached work; the medians are kept.
CACHED_PASSES = 3
#: Bump when what a calibration measures changes: the stored ones are then measured again.
CALIBRATION_VERSION = 1


@dataclass(frozen=True)
class Calibration:
    """Seconds per unit in one process with one thread, measured by `calibrate`: ``features`` per
    image, ``pairs`` per pair matched and verified, and per paradigm ``map_pairs`` per matched pair
    triangulated into a map and ``registered_images`` per database image a query is registered
    against; ``seconds``: what the calibration took; ``sample``: what it ran on; ``cached``: per
    stage, seconds per unit of its work found cached (read back; `stage_totals`' units), and
    `CACHED_OTHER` per registration."""

    features: float
    pairs: float
    map_pairs: dict[str, float]
    registered_images: dict[str, float]
    seconds: float
    sample: str
    cached: dict[str, float] = dataclasses.field(default_factory=dict)


def calibration_sample(scene: Scene) -> tuple[Scene, Ranking]:
    """A neighbourhood of ``scene`` and its ranking: the `CALIBRATION_DATABASE` database images
    nearest (camera centres) to the one nearest the database's centroid, and the
    `CALIBRATION_QUERIES` queries nearest to it (the first ones where queries have no pose), each
    ranking the neighbourhood by distance."""
    database, queries = scene.database, scene.queries
    centres = database.centers
    seed = int(np.argmin(np.linalg.norm(centres - centres.mean(0), axis=1)))
    near = np.argsort(np.linalg.norm(centres - centres[seed], axis=1), kind="stable")[:CALIBRATION_DATABASE]
    posed = np.flatnonzero(queries.has_pose)
    if len(posed):
        order = posed[np.argsort(np.linalg.norm(queries.centers[posed] - centres[seed], axis=1), kind="stable")]
    else:
        order = np.arange(len(queries))
    chosen = order[:CALIBRATION_QUERIES]
    anchors = np.where(queries.has_pose[chosen, None], queries.centers[chosen], centres[seed])
    distances = np.linalg.norm(anchors[:, None] - centres[near][None], axis=2)
    ranked = np.argsort(distances, axis=1, kind="stable")
    ranking = Ranking("calibration", ranked, -np.take_along_axis(distances, ranked, axis=1), "groundtruth")
    sample = Scene(
        f"{scene.name} (calibration)", database.subset(near), queries.subset(chosen), frustum_far=scene.frustum_far
    )
    return sample, ranking


def calibrate(
    scene: Scene, settings: SfmSettings, paradigms: Mapping[str, SfmParadigm], cache_dir: Path
) -> Calibration:
    """Unit costs of the SfM stages, measured by running the pipeline (`run_sfm`) with
    ``paradigms`` on `calibration_sample`, in one process with one thread (as each worker runs
    its tasks), into a temporary folder of ``cache_dir`` deleted afterwards; then `CACHED_PASSES`
    times again over its own cached work (`Calibration.cached`: the median of each stage's time
    per unit of its work, `stage_totals`, and of the rest, `CACHED_OTHER`, per registration)."""
    sample, ranking = calibration_sample(scene)
    one_process = dataclasses.replace(settings, workers=1)
    started = time.perf_counter()
    with temporary_folder(cache_dir, "calibration") as folder, single_threaded(), _quiet():
        run, *again = [
            run_sfm(SfmInputs.prepare(sample, one_process, folder, extract=False), [ranking], paradigms)
            for _ in range(1 + CACHED_PASSES)
        ]

    def per_unit(stage: str, units: float) -> float:
        record = run.stages.get(stage)
        return record.seconds / units if record is not None and units else 0.0

    plan = run.plan
    cached = {
        stage: statistics.median(r.stages[stage].seconds if stage in r.stages else 0.0 for r in again) / units
        for stage, units in stage_totals(plan).items()
        if units
    }
    rest = [max(0.0, r.seconds - sum(record.seconds for record in r.stages.values())) for r in again]
    cached[CACHED_OTHER] = statistics.median(rest) / max(1, sum(work.registrations.total for work in plan.paradigms))
    map_pairs, registered = {}, {}
    for work in plan.paradigms:
        triangulate, register = stage_names(work.paradigm)
        map_pairs[work.paradigm] = per_unit(triangulate, work.maps.new * work.pairs_per_map)
        registered[work.paradigm] = per_unit(register, work.registered_images.new)
    return Calibration(
        per_unit(FEATURES, plan.features.new),
        per_unit(MATCHING, plan.new_pairs()),
        map_pairs,
        registered,
        time.perf_counter() - started,
        f"{len(sample.database)} database images and {len(sample.queries)} queries near the scene's centre",
        cached,
    )


def stage_totals(plan: SfmPlan) -> dict[str, int]:
    """Each stage's work in all, cached or not, in the units of `SfmPlan.stage_units`."""
    totals = {
        FEATURES: plan.features.total,
        MATCHING: max((p.query_pairs.total for p in plan.paradigms), default=0)
        + sum(p.database_pairs.total for p in plan.paradigms),
    }
    for work in plan.paradigms:
        triangulate, register = stage_names(work.paradigm)
        totals[triangulate], totals[register] = work.maps.total, work.registrations.total
    return totals


def stored_calibration(
    scene: Scene, settings: SfmSettings, paradigms: Mapping[str, SfmParadigm], cache_dir: Path
) -> tuple[Calibration, Path, bool]:
    """``(calibration, its file, whether it was stored)``: the `calibrate` of these settings on this
    scene's sample and this machine, measured once and kept in ``cache_dir/forecast/``."""
    sample, _ = calibration_sample(scene)
    key = config_key(
        CALIBRATION_VERSION,
        repr(dataclasses.replace(settings, workers=1)),
        {name: repr(paradigm) for name, paradigm in paradigms.items()},
        sample.database.fingerprint(),
        sample.queries.fingerprint(),
        platform.node(),
        os.cpu_count(),
    )
    path = cache_dir / "forecast" / f"calibration-{key}.npz"
    if path.is_file():
        return calibration_from_arrays(load_arrays(path), path), path, True
    calibration = calibrate(scene, settings, paradigms, cache_dir)
    save_arrays(path, calibration_arrays(calibration))  # no lock: two dry runs measuring at once keep either
    return calibration, path, False


def calibration_arrays(calibration: Calibration) -> dict[str, np.ndarray]:
    """``calibration`` as the arrays of its cache file: one per value, a mapping's as ``<field>:<key>``."""
    arrays = {"sample": np.asarray(calibration.sample)}
    for field in dataclasses.fields(Calibration):
        value = getattr(calibration, field.name)
        if isinstance(value, dict):
            arrays.update({f"{field.name}:{key}": np.float64(number) for key, number in value.items()})
        elif field.name != "sample":
            arrays[field.name] = np.float64(value)
    return arrays


def calibration_from_arrays(arrays: Mapping[str, np.ndarray], path: Path) -> Calibration:
    """The `Calibration` of a cache file's ``arrays`` (`calibration_arrays`); a `DataFileError`
    naming ``path`` when they are not one."""
    from locretrieval.errors import DELETE_CACHE_FILE, DataFileError

    values: dict[str, Any] = {"map_pairs": {}, "registered_images": {}, "cached": {}}
    try:
        for name, array in arrays.items():
            field, _, key = name.partition(":")
            if key:
                values[field][key] = float(array)
            else:
                values[field] = str(array) if field == "sample" else float(array)
        if CACHED_OTHER not in values["cached"]:
            raise KeyError(f"cached costs {sorted(values['cached'])}")
        return Calibration(**values)
    except (TypeError, ValueError, KeyError) as error:
        raise DataFileError(path, f"not a forecast's calibration ({error})", DELETE_CACHE_FILE) from None


def after_groundtruth(
    plan: SfmPlan, inputs: SfmInputs, database_pairs: set[tuple[str, str]], query_pairs: set[tuple[str, str]]
) -> tuple[SfmPlan, dict[str, Work]]:
    """The paradigms' work once the ground truth has matched ``database_pairs`` and ``query_pairs``
    (names): their new pairs at most the pairs left, a map every query shares of the same pairs
    (the global map's, ``sfm.map_pairs``) matched already; and the ground truth's own work, as
    stages (`GROUNDTRUTH_MATCHING`: new pairs, `GROUNDTRUTH_MAP`: the joint map's pairs)."""
    scene = inputs.scene
    database_pairs = set(inputs.database_pairs.canonical(database_pairs))
    query_pairs = set(inputs.query_pairs.canonical(query_pairs))
    new = len(inputs.database_pairs.raw.missing(map(pair_key, database_pairs))) + len(
        inputs.query_pairs.raw.missing(map(pair_key, query_pairs))
    )
    all_query_pairs = len(scene.queries) * len(scene.database)
    all_database_pairs = comb(len(scene.database), 2)
    paradigms = []
    for work in plan.paradigms:
        query_left = min(work.query_pairs.new, all_query_pairs - len(query_pairs))
        database_left = 0 if work.shared_map else min(work.database_pairs.new, all_database_pairs - len(database_pairs))
        paradigms.append(
            dataclasses.replace(
                work,
                query_pairs=Work(work.query_pairs.total, max(0, query_left)),
                database_pairs=Work(work.database_pairs.total, max(0, database_left)),
            )
        )
    groundtruth = {
        GROUNDTRUTH_MATCHING: Work(len(database_pairs) + len(query_pairs), new),
        GROUNDTRUTH_MAP: Work(len(database_pairs) + len(query_pairs), len(database_pairs) + len(query_pairs)),
    }
    return dataclasses.replace(plan, paradigms=paradigms), groundtruth


def forecast(
    plan: SfmPlan,
    calibration: Calibration,
    processes: int,
    matching_device: str,
    groundtruth: Mapping[str, Work] | None = None,
) -> dict[str, float]:
    """Seconds per stage: ``plan``'s new units (and the ``groundtruth``'s, `after_groundtruth`)
    times ``calibration``'s unit costs, spread over ``processes`` workers where the pipeline
    spreads them (matching on a GPU and a map every query shares in one process); plus reading
    back the work found cached (`stage_totals` less the new, `Calibration.cached`) and
    `CACHED_OTHER` per registration, in this process."""
    matching_processes = processes if matching_device == "cpu" else 1
    seconds = {FEATURES: plan.features.new * calibration.features / processes}
    groundtruth = groundtruth or {}
    if groundtruth and groundtruth[GROUNDTRUTH_MATCHING].total:  # the ground truth matches first
        seconds[GROUNDTRUTH_MATCHING] = groundtruth[GROUNDTRUTH_MATCHING].new * calibration.pairs / matching_processes
        shared = next((w.paradigm for w in plan.paradigms if w.shared_map), None)
        per_pair = calibration.map_pairs.get(shared, 0.0) if shared else max(calibration.map_pairs.values(), default=0)
        seconds[GROUNDTRUTH_MAP] = groundtruth[GROUNDTRUTH_MAP].new * per_pair
    seconds[MATCHING] = plan.new_pairs() * calibration.pairs / matching_processes
    for work in plan.paradigms:
        triangulate, register = stage_names(work.paradigm)
        map_seconds = work.maps.new * work.pairs_per_map * calibration.map_pairs[work.paradigm]
        seconds[triangulate] = map_seconds if work.shared_map else map_seconds / processes
        seconds[register] = work.registered_images.new * calibration.registered_images[work.paradigm] / processes
    if calibration.cached:
        new = plan.stage_units()
        for stage, total in stage_totals(plan).items():
            seconds[stage] += max(0, total - new[stage][0]) * calibration.cached.get(stage, 0.0)
        registrations = sum(work.registrations.total for work in plan.paradigms)
        seconds[CACHED_OTHER] = registrations * calibration.cached[CACHED_OTHER]
    return seconds


def describe_forecast(seconds: Mapping[str, float], calibration: Calibration, processes: int) -> str:
    """The forecast as log lines: per stage, the total and the band it claims, and what was measured."""
    low, high = BAND
    total = sum(seconds.values())
    return "\n".join(
        [
            f"  calibrated in {calibration.seconds:.1f} s on {calibration.sample}, in one process: features "
            f"{calibration.features:.2f} s/image, match + verify {calibration.pairs * 1e3:.1f} ms/pair, "
            + ", ".join(
                f"{name} {calibration.map_pairs[name] * 1e3:.2f} ms/map pair and "
                f"{calibration.registered_images[name] * 1e3:.2f} ms/registered image"
                for name in calibration.map_pairs
            )
            + f"; spread over {processes} worker process(es); counting + gathering "
            + f"{calibration.cached.get(CACHED_OTHER, 0.0) * 1e3:.2f} ms/registration",
            "  forecast: " + ", ".join(f"{stage} {duration(value)}" for stage, value in seconds.items()),
            f"  total {duration(total)}: the run should take {duration(total * low)} to {duration(total * high)} "
            f"(x{low:g}-{high:g}) on a machine as loaded as now",
        ]
    )


def counted_plan(
    inputs: SfmInputs, rankings: Sequence[Ranking], paradigms: Mapping[str, SfmParadigm], num_rankings: int
) -> SfmPlan:
    """The work of ``paradigms``: exact for ``rankings`` (cached work as cached, `count_work`),
    plus upper bounds for ``num_rankings`` more not computed yet (a map every query shares counted once)."""
    if not rankings or not num_rankings:
        return count_work(inputs, rankings or None, paradigms, num_rankings)
    exact, bound = count_work(inputs, rankings, paradigms), count_work(inputs, None, paradigms, num_rankings)

    def added(a: ParadigmWork, b: ParadigmWork) -> ParadigmWork:
        def add(x: Work, y: Work) -> Work:
            return Work(x.total + y.total, x.new + y.new)

        summed = ("query_pairs", "registrations", "registered_images", "queries")
        if not a.shared_map:  # a map every query shares is one, whichever the rankings
            summed += ("database_pairs", "maps")
        return dataclasses.replace(a, **{name: add(getattr(a, name), getattr(b, name)) for name in summed})

    return SfmPlan(exact.features, [added(a, b) for a, b in zip(exact.paradigms, bound.paradigms)], exact=False)


def dry_run_forecast(
    scene: Scene,
    settings: SfmSettings,
    paradigms: Mapping[str, SfmParadigm],
    cache_dir: Path,
    rankings: Sequence[Ranking],
    num_rankings: int,
    groundtruth_pairs: tuple[set[tuple[str, str]], set[tuple[str, str]]],
) -> tuple[SfmPlan, dict[str, float], str]:
    """The dry run of ``paradigms`` on ``scene`` with the ``rankings`` the caches hold,
    ``num_rankings`` more to come and the pairs of the ground truth to compute
    (`groundtruth_sfm_pairs`): the plan (`counted_plan`), each stage's forecast seconds (the
    calibration `stored_calibration` keeps) and the log lines saying both."""
    inputs = SfmInputs.prepare(scene, settings, cache_dir, extract=False)
    plan, groundtruth = after_groundtruth(
        counted_plan(inputs, rankings, paradigms, num_rankings), inputs, *groundtruth_pairs
    )
    calibration, path, stored = stored_calibration(scene, settings, paradigms, cache_dir)
    seconds = forecast(plan, calibration, settings.processes, settings.matching.matcher().device, groundtruth)
    lines = [plan.describe()]
    if groundtruth[GROUNDTRUTH_MATCHING].total:
        lines.append(f"  ground truth: pairs {groundtruth[GROUNDTRUTH_MATCHING]}, matched first")
    lines.append(describe_forecast(seconds, calibration, settings.processes))
    lines.append(
        f"  unit costs {'read from' if stored else 'measured now and kept in'} {path} (delete it to measure again)"
    )
    return plan, seconds, "\n".join(lines)


def duration(seconds: float) -> str:
    """Seconds as a short duration (s, min or h)."""
    if seconds < 120:
        return f"{seconds:.1f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """The pipeline's and the paradigms' log below warnings while they calibrate (not the run's lines)."""
    loggers = [logging.getLogger(name) for name in ("locretrieval.sfm", "locretrieval.paradigms")]
    levels = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)
