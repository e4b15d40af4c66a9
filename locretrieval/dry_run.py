"""A dry run (``locretrieval evaluate dry_run=true``): the SfM work a run would do and its time
forecast (`locretrieval.paradigms.forecast`), nothing of the run computed or written.

The rankings the caches already hold (the model's descriptors, each ground truth) and the random
baseline (drawn in no time) are read (`stored_rankings`): their work is counted exactly, what is
cached as cached; the work of the others is bounded. The unit costs of the forecast are measured
once per machine and settings and kept in the cache, so that two dry runs forecast the same.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

from locretrieval.benchmark import BenchmarkSettings, build_rankings
from locretrieval.cache import NotCached, stored_only
from locretrieval.groundtruth import GroundTruthSettings, compute_groundtruths
from locretrieval.groundtruth.compute import groundtruth_sfm_pairs
from locretrieval.retrieval import Ranking
from locretrieval.retrieval.descriptors import DescriptorSearch
from locretrieval.scene import Scene

log = logging.getLogger(__name__)


def dry_run(
    scene: Scene,
    model: Any,
    settings: BenchmarkSettings,
    groundtruths: GroundTruthSettings,
    cache_dir: Path,
    random_seed: int | None,
) -> None:
    """Log the SfM work of a run and its forecast (``random_seed``: that of its random baseline, None
    without one): exact for the rankings the
    caches hold, upper bounds for the others (`stored_rankings`); the ground truths not cached
    match their pairs first. No descriptor, ground truth or file of the run is computed or written."""
    paradigms = settings.paradigms.sfm_paradigms()
    if not paradigms:
        log.info("dry run: no SfM paradigm is enabled, nothing to match")
        return
    from locretrieval.paradigms.forecast import dry_run_forecast

    posed = bool(scene.queries.has_pose.any())
    rankings, missing = stored_rankings(scene, model, settings, groundtruths if posed else None, random_seed, cache_dir)
    to_compute = [name for name in groundtruths.parsed() if f"gt_{name}" in missing]
    pairs = (set(), set())
    if to_compute:
        pairs = groundtruth_sfm_pairs(scene, dataclasses.replace(groundtruths, enabled=to_compute), settings.sfm)
    _, _, lines = dry_run_forecast(scene, settings.sfm, paradigms, cache_dir, rankings, len(missing), pairs)
    log.info(
        "dry run over %d rankings; known without computing (from the caches; random: drawn), their work counted "
        "exactly and cached work as cached: %s; not computed yet, their work bounded: %s; nothing of the run is "
        "computed or written:\n%s",
        len(rankings) + len(missing),
        ", ".join(ranking.name for ranking in rankings) or "none",
        ", ".join(missing) or "none",
        lines,
    )


def stored_rankings(
    scene: Scene,
    model: Any,
    settings: BenchmarkSettings,
    groundtruths: GroundTruthSettings | None,
    random_seed: int | None,
    cache_dir: Path,
) -> tuple[list[Ranking], list[str]]:
    """``(rankings, missing)``: the run's rankings that need no computing (the model's when its
    descriptors are cached or it reads them from files, each ground truth of ``groundtruths``
    that is cached, the random one with a ``random_seed``), and the names of the others."""
    missing = []
    with stored_only():
        try:
            given = model.rankings(scene, DescriptorSearch(settings.retrieval, cache_dir))
        except NotCached:
            given, missing = [], [model.name]
        found = {}
        for name in groundtruths.parsed() if groundtruths is not None else {}:
            try:
                one = dataclasses.replace(groundtruths, enabled=[name])
                found.update(compute_groundtruths(scene, one, settings.sfm, cache_dir))
            except NotCached:
                missing.append(f"gt_{name}")
    return build_rankings(scene, {}, found, settings.retrieval, random_seed, given), missing
