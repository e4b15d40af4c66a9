"""The run behind ``evaluate.py``: compute (`locretrieval.benchmark`), write, report, from the objects
the build step made of the config (`Evaluation`, `locretrieval.build.build_evaluation`)."""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from locretrieval.benchmark import (
    BenchmarkResult,
    BenchmarkSettings,
    benchmark,
    build_rankings,
    check_supported,
    relevances,
    run_sfm_shard,
    scene_subsets,
)
from locretrieval.cache import safe_name, save_arrays
from locretrieval.errors import require_built
from locretrieval.estimates import estimated_pose_table
from locretrieval.groundtruth import GroundTruthSettings, compute_groundtruths, statistics_table
from locretrieval.metrics.localization import median_errors
from locretrieval.metrics.subsets import SubsetSettings, missing_mask_inputs
from locretrieval.metrics.uncertainty import Uncertainty
from locretrieval.pool import cpu_time
from locretrieval.report.gallery import GallerySettings, write_gallery_inputs
from locretrieval.report.markdown import best_localization
from locretrieval.report.scene_view import SCENE_VIEW_FILE, SceneViewSettings, write_scene_view
from locretrieval.report.tables import SFM_STAGES
from locretrieval.retrieval.descriptors import DescriptorSearch
from locretrieval.scene import Scene
from locretrieval.scene.ltvl import write_ltvl
from locretrieval.shard import Shard

log = logging.getLogger(__name__)


@dataclass
class ReportSettings:
    """The ``report`` section of evaluate.yaml: the ground truth of the correlations and subset figures
    (``groundtruth``; None: relative pose), the ``figure_formats`` (none: no figure), the ``gallery``
    and the ``scene_view`` (`GallerySettings`, `SceneViewSettings`)."""

    groundtruth: str | None
    figure_formats: list[str]
    gallery: GallerySettings
    scene_view: SceneViewSettings


@dataclass
class Evaluation:
    """What ``evaluate.py`` runs, built from its config by `locretrieval.build.build_evaluation` (every
    key, ``_target_`` and input checked there): the ``scene`` and the ``model``, the ``benchmark``'s
    settings, the ``groundtruth``, ``subsets`` and ``report`` settings, the ``cache_dir``, the random
    baseline's seed (``random_seed``; None: no random baseline), this job's ``shard`` (None: the whole
    run), ``dry_run``, whether to write LTVL files (``ltvl``) and the ``config`` as run (plain data:
    ``config.yaml``)."""

    scene: Scene
    model: Any
    benchmark: BenchmarkSettings
    groundtruth: GroundTruthSettings
    subsets: SubsetSettings
    report: ReportSettings
    cache_dir: Path
    random_seed: int | None
    shard: Shard | None
    dry_run: bool
    ltvl: bool
    config: dict = field(repr=False)


def evaluate(run: Evaluation, output_dir: Path) -> pd.DataFrame:
    """Run the benchmark ``run`` describes and write every output into ``output_dir``.

    The inputs the run needs are checked first (`check_inputs`); with ``dry_run`` the SfM work is only
    counted and forecast (`dry_run`). Writes the tidy tables (``results.csv``, ``query_localized.csv.gz``,
    ``query_errors.csv.gz``, ``median_errors.csv``, ``retrieval.csv``, ``query_retrieval.csv.gz``,
    ``groundtruth_statistics.csv``, ``subsets.csv``, ``estimated_poses.csv.gz``), the rankings, what galleries
    read (``images.csv``, ``relevance/``), LTVL exports, ``summary.json``, the 3D view (``scene_3d.html``, unless
    ``report.scene_view.enabled`` is false) and the report built from those files. Returns the localization
    table. With a ``shard`` the run is one job of a sharded evaluation: it computes the rankings and its
    share of the SfM work into the cache (`run_sfm_shard`), writes nothing else and returns an empty table.
    """
    require_built(run, Evaluation, "build_evaluation")
    started = time.perf_counter()
    scene, model, settings, cache_dir = run.scene, run.model, run.benchmark, run.cache_dir
    groundtruth_settings, subset_settings = run.groundtruth, run.subsets
    log.info("scene %s: %d database images, %d queries", scene.name, len(scene.database), len(scene.queries))
    check_supported(scene, [*settings.paradigms.enabled(), *groundtruth_settings.parsed()])
    check_inputs(scene, model, settings, groundtruth_settings, subset_settings)
    if run.dry_run:
        from locretrieval.dry_run import dry_run

        dry_run(scene, model, settings, groundtruth_settings, cache_dir, run.random_seed)
        return pd.DataFrame()
    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / "config.yaml").write_text(yaml.safe_dump(run.config, sort_keys=False))  # as run, resolved

    described = time.perf_counter()
    with cpu_time() as descriptors_cpu:
        given = model.rankings(scene, DescriptorSearch(settings.retrieval, cache_dir))  # descriptors or a pairs file
    descriptors_seconds = time.perf_counter() - described
    groundtruths, groundtruth_started = {}, time.perf_counter()
    with cpu_time() as groundtruth_cpu:
        if scene.queries.has_pose.any():
            groundtruths = compute_groundtruths(scene, groundtruth_settings, settings.sfm, cache_dir)
        else:
            log.warning(
                "no query has a reference pose: ground truth and metrics are skipped, poses are only exported (ltvl/)"
            )
    groundtruth_seconds = time.perf_counter() - groundtruth_started
    rankings = build_rankings(scene, {}, groundtruths, settings.retrieval, run.random_seed, given)
    if run.shard is not None:  # one job of a sharded evaluation: its SfM work, no results
        run_sfm_shard(scene, rankings, settings, cache_dir, run.shard)
        return pd.DataFrame()
    subsets, subset_table = scene_subsets(scene, subset_settings, cache_dir)
    if run.report.figure_formats:
        from locretrieval.report.painters import start_painters

        start_painters()  # the report's figure workers import matplotlib while the benchmark runs
    relevance = relevances(groundtruths, groundtruth_settings.relevance)
    result = benchmark(scene, rankings, settings, subsets, cache_dir, relevance)

    write_tables(
        result, statistics_table(scene.name, groundtruths), subset_table, settings.metrics.uncertainty, output_dir
    )
    write_gallery_inputs(scene, relevance, output_dir)
    poses = estimated_pose_table(scene.name, result.estimates, scene.queries.names)
    poses.to_csv(output_dir / "estimated_poses.csv.gz", index=False)
    if run.report.scene_view.enabled:
        write_scene_view(
            output_dir / SCENE_VIEW_FILE,
            scene,
            poses,
            global_map_points(scene, settings, cache_dir),
            run.report.scene_view,
        )
    exported = export_ltvl(scene, result, output_dir / "ltvl") if run.ltvl else 0
    summary = {
        "dataset": scene.name,
        "database images": len(scene.database),
        "queries": f"{len(scene.queries)} ({int(scene.queries.has_pose.sum())} with reference poses)",
        "query tags": ", ".join(scene.queries.all_tags) or "none",
        "rankings": ", ".join(f"{r.name} ({r.kind})" for r in rankings),
        "paradigms": ", ".join(f"{p} (k={getattr(settings.paradigms, p).k})" for p in settings.paradigms.enabled()),
        "LTVL exports": f"{exported} files in ltvl/",
        "run time": f"{time.perf_counter() - started:.1f} s",
        "descriptors seconds": round(descriptors_seconds, 2),
        "descriptors CPU seconds": round(descriptors_cpu.seconds, 2),
        "ground truth seconds": round(groundtruth_seconds, 2),
        "ground truth CPU seconds": round(groundtruth_cpu.seconds, 2),
        "SfM seconds": round(result.sfm_seconds, 2),
        SFM_STAGES: result.sfm_stages,  # per stage: seconds, work done, its unit
    }
    if scene.quality is not None:  # a reconstruction's poses: how good that pseudo ground truth is
        summary["pseudo ground truth"] = scene.quality.summary()
    (output_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    from locretrieval.report import build_report  # here: matplotlib is imported when figures are drawn

    build_report(
        [output_dir],
        output_dir,
        run.report.groundtruth,
        list(run.report.figure_formats),
        gallery=run.report.gallery,
        thumbnail_cache=cache_dir / "thumbnails",
        image_roots=None,  # the images of the scene just loaded, wherever its config keeps them
        uncertainty=settings.metrics.uncertainty,
    )
    results = result.localization
    if len(results):
        best = best_localization(results).droplevel("dataset")
        log.info(
            "best %% localized over k, all %d queries (%g %% interval, the k reaching it):\n%s",
            len(scene.queries),
            100 * settings.metrics.uncertainty.confidence,
            best.to_string(),
        )
    log.info("results and report.md in %s", output_dir)
    return results


def check_inputs(
    scene: Scene, model: Any, settings: BenchmarkSettings, groundtruths: GroundTruthSettings, subsets: SubsetSettings
) -> None:
    """Stop before the first expensive stage when inputs the run needs are missing: one
    `FileNotFoundError` names them all (the model's inputs, `GlobalDescriptor.missing_inputs`:
    feature folders or a pairs file; kapture local features, the COLMAP model, dynamic-object masks
    or their Mask R-CNN weights). The model's weight file is checked as it is built, before the
    scene is loaded (`MissingWeightsError`: where its authors publish it)."""
    missing = [
        *(f"model.{problem}" for problem in model.missing_inputs(scene)),
        *local_feature_inputs(scene, settings, groundtruths),
        *paradigm_inputs(settings),
        *missing_mask_inputs(scene.queries, subsets),
    ]
    if missing:
        raise FileNotFoundError(
            f"{len(missing)} missing input(s); nothing was computed:\n" + "\n".join(f"- {m}" for m in missing)
        )


def local_feature_inputs(scene: Scene, settings: BenchmarkSettings, groundtruths: GroundTruthSettings) -> list[str]:
    """The files the local features read (`LocalFeatures.missing_inputs`: e.g. the kapture
    features of both image sets) that are absent, if an SfM paradigm or a ground truth matching
    features needs them."""
    sfm_paradigms = bool(settings.paradigms.sfm_paradigms())
    sfm_groundtruth = any(definition.uses_sfm for definition in groundtruths.parsed().values())
    if not (sfm_paradigms or sfm_groundtruth):
        return []
    features = settings.sfm.features
    return [
        f"sfm.features: {problem}"
        for images in (scene.database, scene.queries)
        for problem in features.missing_inputs(images)
    ]


def paradigm_inputs(settings: BenchmarkSettings) -> list[str]:
    """The files the enabled paradigms read (`Paradigm.missing_inputs`) that are absent."""
    return [
        f"paradigms.{name}.{problem}"
        for name in settings.paradigms.enabled()
        for problem in getattr(settings.paradigms, name).missing_inputs()
    ]


def global_map_points(scene: Scene, settings: BenchmarkSettings, cache_dir: Path) -> np.ndarray | None:
    """The points (world, metres) of the first enabled paradigm's map that was built
    (`Paradigm.map_points`), else ``None``."""
    for name in settings.paradigms.enabled():
        points = getattr(settings.paradigms, name).map_points(scene, settings.sfm, cache_dir)
        if points is not None:
            return points
    return None


def write_tables(
    result: BenchmarkResult,
    groundtruth_statistics: pd.DataFrame,
    subset_table: pd.DataFrame,
    uncertainty: Uncertainty,
    output_dir: Path,
) -> None:
    """The tidy tables and the rankings of a run (see `evaluate`); the median errors' intervals at ``uncertainty``."""
    for ranking in result.rankings:
        arrays = {
            "indices": ranking.indices,
            "scores": ranking.scores,
            "kind": np.asarray(ranking.kind),
            "name": np.asarray(ranking.name),
        }
        save_arrays(output_dir / "rankings" / f"{safe_name(ranking.name)}.npz", arrays)
    result.localization.to_csv(output_dir / "results.csv", index=False)
    result.query_localized.to_csv(output_dir / "query_localized.csv.gz", index=False)
    result.query_errors.to_csv(output_dir / "query_errors.csv.gz", index=False)
    median_errors(result.query_errors, uncertainty).to_csv(output_dir / "median_errors.csv", index=False)
    groundtruth_statistics.to_csv(output_dir / "groundtruth_statistics.csv", index=False)
    subset_table.to_csv(output_dir / "subsets.csv", index=False)
    if len(result.retrieval.columns):
        result.retrieval.to_csv(output_dir / "retrieval.csv", index=False)
        result.query_retrieval.to_csv(output_dir / "query_retrieval.csv.gz", index=False)


def export_ltvl(scene: Scene, result: BenchmarkResult, folder: Path) -> int:
    """Write one LTVL file per ranking x paradigm x method x k (images named per
    ``scene.ltvl_names``); returns how many were written."""
    written = skipped = 0
    for e in result.estimates:
        for n, k in enumerate(e.ks):
            path = folder / safe_name(e.ranking) / f"{e.paradigm}_{e.method}_k{k}.txt"
            path.parent.mkdir(parents=True, exist_ok=True)
            missing = write_ltvl(path, scene.queries.names, e.qvec[n], e.tvec[n], scene.ltvl_names)
            log.debug("%s: %d queries without an estimate are not in the file", path, missing)
            written, skipped = written + 1, skipped + missing
    log.info(
        "%d LTVL files in %s; queries without an estimate (%d in all, see query_errors.csv.gz) are left out",
        written,
        folder,
        skipped,
    )
    return written
