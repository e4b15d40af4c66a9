"""The run behind ``evaluate.py``: instantiate, compute (`locretrieval.benchmark`), write, report."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import pandas as pd
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from locretrieval.benchmark import BenchmarkResult, BenchmarkSettings, benchmark, build_rankings, relevances, scene_subsets
from locretrieval.cache import save_arrays
from locretrieval.config import validated
from locretrieval.groundtruth import GroundTruthSettings, compute_groundtruths, statistics_table
from locretrieval.metrics.localization import best_over_k
from locretrieval.metrics.subsets import SubsetSettings
from locretrieval.report import build_report
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.scene import Scene
from locretrieval.scene.kapture_io import write_ltvl

log = logging.getLogger(__name__)


def evaluate(cfg: DictConfig, output_dir: Path) -> pd.DataFrame:
    """Run the benchmark configured by ``cfg`` and write every output into ``output_dir``.

    Every config section is checked before any work. Writes the tidy tables
    (``results.csv``, ``query_errors.csv.gz``, ``retrieval.csv``, ``query_retrieval.csv.gz``,
    ``groundtruth_statistics.csv``, ``subsets.csv``), the rankings, LTVL exports,
    ``summary.json`` and the report built from those tables. Returns the localization table.
    """
    started = time.perf_counter()
    settings = BenchmarkSettings.from_config(cfg)
    groundtruth_settings = validated(GroundTruthSettings, cfg.groundtruth, "groundtruth")
    subset_settings = validated(SubsetSettings, cfg.subsets, "subsets")
    output_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, output_dir / "config.yaml", resolve=True)  # as run; .hydra/ keeps the interpolations
    cache_dir = Path(cfg.paths.cache_dir)
    scene: Scene = instantiate(cfg.data)
    log.info("scene %s: %d database images, %d queries", scene.name, len(scene.database), len(scene.queries))

    model = instantiate(cfg.model)
    descriptors = describe_scene(model, scene, cache_dir)
    groundtruths = {}
    if scene.queries.has_pose.any():
        groundtruths = compute_groundtruths(scene, groundtruth_settings, settings.sfm, cache_dir)
    else:
        log.warning("no query has a reference pose: ground truth and metrics are skipped, poses are only exported (ltvl/)")
    random_seed = int(cfg.seed) if cfg.baselines.random else None
    rankings = build_rankings(scene, {model.name: descriptors}, groundtruths, settings.retrieval, random_seed)
    subsets, subset_table = scene_subsets(scene, subset_settings, cache_dir, str(cfg.device))
    result = benchmark(scene, rankings, settings, subsets, cache_dir, relevances(groundtruths))

    write_tables(result, statistics_table(scene.name, groundtruths), subset_table, output_dir)
    exported = export_ltvl(scene, result, output_dir / "ltvl") if cfg.output.ltvl else 0
    summary = {
        "dataset": scene.name,
        "database images": len(scene.database),
        "queries": f"{len(scene.queries)} ({int(scene.queries.has_pose.sum())} with reference poses)",
        "query tags": ", ".join(scene.queries.all_tags) or "none",
        "rankings": ", ".join(f"{r.name} ({r.kind})" for r in rankings),
        "paradigms": ", ".join(f"{p} (k={getattr(settings.paradigms, p).k})" for p in settings.paradigms.enabled()),
        "LTVL exports": f"{exported} files in ltvl/",
        "run time": f"{time.perf_counter() - started:.1f} s",
    }
    (output_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    build_report([output_dir], output_dir, cfg.report.groundtruth, list(cfg.report.figure_formats))
    results = result.localization
    if len(results):
        best = best_over_k(results[results["subset"] == "all"], "position_threshold_m")
        log.info("best %% localized over k, all queries:\n%s", best.to_string())
    log.info("results and report.md in %s", output_dir)
    return results


def write_tables(result: BenchmarkResult, groundtruth_statistics: pd.DataFrame, subset_table: pd.DataFrame, output_dir: Path) -> None:
    """The tidy tables and the rankings of a run (see `evaluate`)."""
    for ranking in result.rankings:
        save_arrays(output_dir / "rankings" / f"{ranking.name}.npz", {"indices": ranking.indices, "scores": ranking.scores})
    result.localization.to_csv(output_dir / "results.csv", index=False)
    result.query_errors.to_csv(output_dir / "query_errors.csv.gz", index=False)
    groundtruth_statistics.to_csv(output_dir / "groundtruth_statistics.csv", index=False)
    subset_table.to_csv(output_dir / "subsets.csv", index=False)
    if len(result.retrieval.columns):
        result.retrieval.to_csv(output_dir / "retrieval.csv", index=False)
        result.query_retrieval.to_csv(output_dir / "query_retrieval.csv.gz", index=False)


def export_ltvl(scene: Scene, result: BenchmarkResult, folder: Path) -> int:
    """Write one LTVL file per ranking x paradigm x method x k (images named per
    ``scene.ltvl_name_style``); returns how many were written."""
    written = skipped = 0
    for e in result.estimates:
        for n, k in enumerate(e.ks):
            path = folder / e.ranking / f"{e.paradigm}_{e.method}_k{k}.txt"
            path.parent.mkdir(parents=True, exist_ok=True)
            missing = write_ltvl(path, scene.queries.names, e.qvec[n], e.tvec[n], name_style=scene.ltvl_name_style)
            log.debug("%s: %d queries without an estimate are not in the file", path, missing)
            written, skipped = written + 1, skipped + missing
    log.info("%d LTVL files in %s; queries without an estimate (%d in all, see query_errors.csv.gz) are left out", written, folder, skipped)
    return written
