"""The benchmark run behind ``evaluate.py``: rankings -> paradigms -> metrics -> tables -> report."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import pandas as pd
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from scipy import sparse

from locretrieval.cache import save_arrays
from locretrieval.groundtruth import compute_groundtruths
from locretrieval.localization import PARADIGMS, PoseEstimates
from locretrieval.metrics.localization import localization_table, query_error_table, query_subsets
from locretrieval.metrics.retrieval import retrieval_tables
from locretrieval.metrics.subsets import image_subsets
from locretrieval.report import build_report
from locretrieval.report.markdown import best_over_k
from locretrieval.retrieval import Ranking, random_ranking
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.retrieval.index import search
from locretrieval.scene import Scene
from locretrieval.scene.kapture_io import write_ltvl

log = logging.getLogger(__name__)


def evaluate(cfg: DictConfig, output_dir: Path) -> pd.DataFrame:
    """Run the benchmark configured by ``cfg`` and write every output into ``output_dir``.

    Writes the tidy tables (``results.csv``, ``query_errors.csv.gz``, ``retrieval.csv``,
    ``query_retrieval.csv.gz``, ``groundtruth_statistics.csv``, ``subsets.csv``), the rankings,
    LTVL exports, ``summary.json`` and the report built from those tables. Returns the
    localization table.
    """
    started = time.perf_counter()
    output_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, output_dir / "config.yaml", resolve=True)  # as run; .hydra/ keeps the interpolations
    cache_dir = Path(cfg.paths.cache_dir)
    scene: Scene = instantiate(cfg.data)
    log.info("scene %s: %d database images, %d queries", scene.name, len(scene.database), len(scene.queries))

    rankings, relevances, groundtruth_statistics = build_rankings(cfg, scene, cache_dir)
    for ranking in rankings:
        save_arrays(output_dir / "rankings" / f"{ranking.name}.npz", {"indices": ranking.indices, "scores": ranking.scores})

    enabled = enabled_paradigms(cfg.paradigms)
    estimates: list[PoseEstimates] = []
    for paradigm in enabled:
        log.info("paradigm %s, k=%s", paradigm, list(cfg.paradigms[paradigm].k))
        estimates += PARADIGMS[paradigm](scene, rankings, cfg.paradigms[paradigm], cache_dir)

    subset_masks, subset_table = image_subsets(scene.name, scene.queries, cfg.subsets, cache_dir, cfg.device)
    tag_subsets = query_subsets(scene.queries)
    if set(tag_subsets) & set(subset_masks):
        raise ValueError(f"query tags {sorted(set(tag_subsets) & set(subset_masks))} clash with the subsets of configs/subsets")
    subsets = tag_subsets | subset_masks
    thresholds = [list(map(float, pair)) for pair in cfg.metrics.thresholds]
    results = localization_table(scene.name, estimates, scene.queries, thresholds, subsets)
    results.to_csv(output_dir / "results.csv", index=False)
    query_error_table(scene.name, estimates, scene.queries).to_csv(output_dir / "query_errors.csv.gz", index=False)
    groundtruth_statistics.to_csv(output_dir / "groundtruth_statistics.csv", index=False)
    subset_table.to_csv(output_dir / "subsets.csv", index=False)
    if relevances:
        paradigm_ks = sorted({int(k) for p in enabled for k in cfg.paradigms[p].k})
        retrieval, query_retrieval = retrieval_tables(
            scene.name, rankings, relevances, scene.queries, subsets, range(1, int(cfg.retrieval.depth) + 1), paradigm_ks
        )
        retrieval.to_csv(output_dir / "retrieval.csv", index=False)
        query_retrieval.to_csv(output_dir / "query_retrieval.csv.gz", index=False)
    exported = export_ltvl(cfg, scene, estimates, output_dir / "ltvl")

    summary = {
        "dataset": scene.name,
        "database images": len(scene.database),
        "queries": f"{len(scene.queries)} ({int(scene.queries.has_pose.sum())} with reference poses)",
        "query tags": ", ".join(scene.queries.all_tags) or "none",
        "rankings": ", ".join(f"{r.name} ({r.kind})" for r in rankings),
        "paradigms": ", ".join(f"{p} (k={list(cfg.paradigms[p].k)})" for p in enabled),
        "LTVL exports": f"{exported} files in ltvl/",
        "run time": f"{time.perf_counter() - started:.1f} s",
    }
    (output_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    build_report([output_dir], output_dir, cfg.report.groundtruth, list(cfg.report.figure_formats))
    if len(results):
        best = best_over_k(results[results["subset"] == "all"], "position_threshold_m")
        log.info("best %% localized over k, all queries:\n%s", best.to_string())
    log.info("results and report.md in %s", output_dir)
    return results


def build_rankings(
    cfg: DictConfig, scene: Scene, cache_dir: Path
) -> tuple[list[Ranking], dict[str, sparse.csr_matrix], pd.DataFrame]:
    """The descriptor ranking, the ground-truth rankings (queries with poses) and baselines.

    Also returns each ground truth's relevance matrix and its Table 1 statistics.
    """
    depth = int(cfg.retrieval.depth)
    model = instantiate(cfg.model)
    database_descriptors, query_descriptors = describe_scene(model, scene, cache_dir)
    rankings = [search(query_descriptors, database_descriptors, depth=depth, name=model.name, chunk_size=int(cfg.retrieval.chunk_size))]
    relevances, statistics = {}, []
    if scene.queries.has_pose.any():
        for name, groundtruth in compute_groundtruths(scene.database, scene.queries, cfg.groundtruth, cache_dir=cache_dir).items():
            rankings.append(groundtruth.ranking)
            relevances[name] = groundtruth.relevance
            statistics.append({"dataset": scene.name, "groundtruth": name, **groundtruth.statistics()})
    else:
        log.warning("no query has a reference pose: ground truth and metrics are skipped, poses are only exported (ltvl/)")
    if cfg.baselines.random:
        rankings.append(random_ranking(len(scene.queries), len(scene.database), depth, int(cfg.seed)))
    check_unique_names(rankings)
    return rankings, relevances, pd.DataFrame(statistics)


#: Sections of ``configs/paradigms`` that are not paradigms.
SHARED_PARADIGM_SECTIONS = ("k", "sfm")


def enabled_paradigms(config: DictConfig) -> list[str]:
    """The paradigms enabled in ``config`` (``configs/paradigms``), in the order of `PARADIGMS`."""
    unknown = sorted(set(config) - set(PARADIGMS) - set(SHARED_PARADIGM_SECTIONS))
    if unknown:
        raise ValueError(f"paradigms: unknown sections {unknown}; the paradigms are {sorted(PARADIGMS)}")
    return [p for p in PARADIGMS if p in config and config[p].enabled]


def check_unique_names(rankings: list[Ranking]) -> None:
    """Ranking names label every table row and output folder: two rankings must not share one."""
    names = [r.name for r in rankings]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"rankings {repeated} are named twice ({names}): rename the model (model.name=...)")


def export_ltvl(cfg: DictConfig, scene: Scene, estimates: list[PoseEstimates], folder: Path) -> int:
    """Write one LTVL file per ranking x paradigm x method x k; returns how many were written."""
    if not cfg.output.ltvl:
        return 0
    written = skipped = 0
    for e in estimates:
        for n, k in enumerate(e.ks):
            path = folder / e.ranking / f"{e.paradigm}_{e.method}_k{k}.txt"
            path.parent.mkdir(parents=True, exist_ok=True)
            missing = write_ltvl(path, scene.queries.names, e.qvec[n], e.tvec[n], name_style=cfg.data.ltvl_name_style)
            log.debug("%s: %d queries without an estimate are not in the file", path, missing)
            written, skipped = written + 1, skipped + missing
    log.info("%d LTVL files in %s; queries without an estimate (%d in all, see query_errors.csv.gz) are left out", written, folder, skipped)
    return written
