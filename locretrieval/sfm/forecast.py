"""The forecast of a dry run (``evaluate.py dry_run=true``): what the SfM work will take here.

No run imports this module: a run measures its stages where they run (`StageMeter`). A dry run
counts the work before any ranking is computed (`count_work`: upper bounds, each ranking's top-k
taken as disjoint, less the pairs the ground truth matches first), then times the costly stages
once on this machine (`calibrate`: the pipeline on a small neighbourhood of the scene, in one
process with one thread, into a temporary folder) and multiplies: features per image, matching
per pair, triangulation per matched pair in a map, registration per database image a query is
registered against, each spread over the worker processes. A machine busier than when calibrated
takes longer; the forecast claims the measured run within `BAND` of it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from math import comb
from pathlib import Path

import numpy as np

from locretrieval.cache import temporary_folder
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene
from locretrieval.sfm.inputs import SfmInputs, SfmSettings
from locretrieval.sfm.matching import pair_key
from locretrieval.sfm.pipeline import SfmStages, count_work, run_sfm
from locretrieval.sfm.work import FEATURES, MATCHING, SfmPlan, Work, stage_names
from locretrieval.threads import single_threaded

log = logging.getLogger(__name__)

#: The measured run's SfM seconds are claimed within these factors of the forecast.
BAND = (0.5, 2.0)
#: Database images and queries of the calibration's neighbourhood: a few seconds of work.
CALIBRATION_DATABASE = 12
CALIBRATION_QUERIES = 3
#: The ground truth's own matching and joint map, forecast as stages of their own.
GROUNDTRUTH_MATCHING, GROUNDTRUTH_MAP = "ground truth: match + verify", "ground truth: triangulate"


@dataclass(frozen=True)
class Calibration:
    """Seconds per unit in one process with one thread, measured by `calibrate`: ``features`` per
    image, ``pairs`` per pair matched and verified, and per paradigm ``map_pairs`` per matched pair
    triangulated into a map and ``registered_images`` per database image a query is registered
    against; ``seconds``: what the calibration took; ``sample``: what it ran on."""

    features: float
    pairs: float
    map_pairs: dict[str, float]
    registered_images: dict[str, float]
    seconds: float
    sample: str


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


def calibrate(scene: Scene, settings: SfmSettings, paradigms: Mapping[str, SfmStages], cache_dir: Path) -> Calibration:
    """Unit costs of the SfM stages, measured by running the pipeline (`run_sfm`) with
    ``paradigms`` on `calibration_sample`, in one process with one thread (as each worker runs
    its tasks), into a temporary folder of ``cache_dir`` deleted afterwards."""
    sample, ranking = calibration_sample(scene)
    one_process = dataclasses.replace(settings, workers=1)
    started = time.perf_counter()
    with temporary_folder(cache_dir, "calibration") as folder, single_threaded(), _quiet():
        inputs = SfmInputs.prepare(sample, one_process, folder, extract=False)
        run = run_sfm(inputs, [ranking], paradigms)

    def per_unit(stage: str, units: float) -> float:
        record = run.stages.get(stage)
        return record.seconds / units if record is not None and units else 0.0

    plan = run.plan
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
    )


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
    spreads them (matching on a GPU and a map every query shares in one process)."""
    matching_processes = processes if matching_device == "cpu" else 1
    seconds = {FEATURES: plan.features.new * calibration.features / processes}
    groundtruth = groundtruth or {}
    if groundtruth:
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
            + f"; spread over {processes} worker process(es)",
            "  forecast: " + ", ".join(f"{stage} {duration(value)}" for stage, value in seconds.items()),
            f"  total {duration(total)}: the run should take {duration(total * low)} to {duration(total * high)} "
            f"(x{low:g}-{high:g}) on a machine as loaded as now",
        ]
    )


def dry_run_forecast(
    scene: Scene,
    settings: SfmSettings,
    paradigms: Mapping[str, SfmStages],
    cache_dir: Path,
    num_rankings: int,
    groundtruth_pairs: tuple[set[tuple[str, str]], set[tuple[str, str]]],
) -> tuple[SfmPlan, dict[str, float], str]:
    """The dry run of ``paradigms`` on ``scene`` with ``num_rankings`` rankings to come and the
    ground truth's pairs (`groundtruth_sfm_pairs`): the plan, each stage's forecast seconds and
    the log lines saying both."""
    inputs = SfmInputs.prepare(scene, settings, cache_dir, extract=False)
    plan, groundtruth = after_groundtruth(count_work(inputs, None, paradigms, num_rankings), inputs, *groundtruth_pairs)
    calibration = calibrate(scene, settings, paradigms, cache_dir)
    seconds = forecast(plan, calibration, settings.processes, settings.matching.matcher().device, groundtruth)
    lines = [plan.describe()]
    if groundtruth[GROUNDTRUTH_MATCHING].total:
        lines.append(f"  ground truth: pairs {groundtruth[GROUNDTRUTH_MATCHING]}, matched first")
    lines.append(describe_forecast(seconds, calibration, settings.processes))
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
