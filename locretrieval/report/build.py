"""`build_report`: the report of one or several finished runs, from their tables alone."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from locretrieval.metrics.comparison import best_k_comparisons, comparison_table, separation
from locretrieval.metrics.correlation import dataset_pearson, dataset_spearman, paired_metrics, query_pearson
from locretrieval.metrics.localization import median_errors
from locretrieval.metrics.retrieval import METRICS
from locretrieval.metrics.uncertainty import Uncertainty, default_uncertainty
from locretrieval.report import markdown, plots, scene_view
from locretrieval.report.gallery import GallerySettings, gallery_section
from locretrieval.report.html import write_html
from locretrieval.report.markdown import md_code, md_text
from locretrieval.report.painters import Painters
from locretrieval.report.published import published_section
from locretrieval.report.tables import SFM_STAGES, RunTables, load_runs

log = logging.getLogger(__name__)

#: Section titles of the retrieval metrics, after the paradigms they stand for (Sec. 4.2).
METRIC_TITLES = {
    "precision": "Landmark retrieval (P@k, paradigm 3a)",
    "recall": "Place recognition (R@k, paradigm 3b)",
    "map": "mAP@k",
}

#: The paired comparisons of every two rankings written next to the report (`comparison_table`).
COMPARISON_FILE = "comparisons.csv"
#: Correlation tables written next to the report.
CORRELATION_FILES = {
    "pearson": "correlation_dataset_pearson.csv",
    "spearman": "correlation_dataset_spearman.csv",
    "query": "correlation_query_pearson.csv.gz",
}


@dataclass
class Comparisons:
    """The paired comparisons of a report: per k (`comparison_table`), at each ranking's best k
    (`best_k_comparisons`), whether each paradigm separates the ground truths from the baseline
    (`separation`), each dataset's position unit and the ``uncertainty`` they were computed at."""

    per_k: pd.DataFrame
    best_k: pd.DataFrame
    separation: pd.DataFrame
    units: dict[str, str]
    uncertainty: Uncertainty


@dataclass
class Correlations:
    """The tables of `paired_metrics`, `dataset_pearson`, `dataset_spearman` and `query_pearson`."""

    paired: pd.DataFrame
    pearson: pd.DataFrame
    spearman: pd.DataFrame
    query: pd.DataFrame


def build_report(
    run_dirs: Sequence[str | Path],
    output_dir: str | Path,
    primary_groundtruth: str | None = None,
    figure_formats: Sequence[str] = ("png", "pdf"),
    figure_workers: int | None = None,
    gallery: GallerySettings | None = None,
    thumbnail_cache: str | Path | None = None,
    image_roots: Sequence[str | Path] | None = (),
    uncertainty: Uncertainty | None = None,
) -> Path:
    """Regenerate ``report.md`` and ``report.html``, ``figures/`` (in ``figure_formats``), ``tables/``
    (Markdown + LaTeX), the correlation tables and, with ``gallery`` settings, the retrieval
    galleries (`gallery_section`, thumbnails cached in ``thumbnail_cache``) in ``output_dir`` from
    the runs at or below ``run_dirs`` (a multirun's runs are concatenated, repeated ground-truth rows dropped).
    Every file read lies inside its run (`locretrieval.report.run_files`); the galleries' images too, or
    inside one of ``image_roots`` (``None``: anywhere, for the report of a run just computed).
    Every two rankings of a dataset are compared on their queries (`Comparisons`, ``comparisons.csv``),
    at ``uncertainty``'s confidence (default: `Uncertainty`'s, the ``metrics.uncertainty`` config's).

    Correlations and the subset figure use ``primary_groundtruth`` (default: the relative
    pose definition, the paper's choice, else the first ground truth by name). Figures are
    drawn by ``figure_workers`` processes (`Painters`: ``None`` or 0, one per core; 1, here).
    Returns the path of ``report.md``.
    """
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    painters = Painters(plots.FigureFolder(output_dir / "figures", tuple(figure_formats)), figure_workers)
    tables = load_runs(run_dirs)
    uncertainty = uncertainty or default_uncertainty()
    comparisons = compute_comparisons(tables, uncertainty)
    comparisons.per_k.to_csv(output_dir / COMPARISON_FILE, index=False)
    correlations = compute_correlations(tables)
    for name, file in CORRELATION_FILES.items():
        getattr(correlations, name).to_csv(output_dir / file, index=False)
    groundtruth = choose_groundtruth(tables.retrieval, primary_groundtruth)
    datasets = sorted(set(tables.results["dataset"]) | set(tables.retrieval["dataset"]))
    writer = markdown.ReportWriter(output_dir, f"locretrieval report: {md_text(', '.join(datasets) or 'no results')}")
    colors = plots.ranking_colors(pd.concat([tables.results["ranking"], tables.retrieval["ranking"]]))
    overview(writer, tables, groundtruth, uncertainty)
    writer.text(*filter(None, [scene_view.link(tables.run_dirs, output_dir)]))
    groundtruth_section(writer, tables)
    localization_section(writer, tables, comparisons, painters, colors)
    published_section(writer, tables.run_dirs)
    retrieval_section(writer, tables, painters, colors)
    revisited_section(writer, tables)
    correlation_section(writer, tables, correlations, groundtruth, painters, colors)
    subset_section(writer, tables, groundtruth, painters, colors)
    failure_section(writer, tables, uncertainty)
    if gallery is not None:
        gallery_section(
            writer,
            tables.run_dirs,
            groundtruth,
            gallery,
            loosest_threshold(tables.results),
            thumbnail_cache,
            image_roots,
            plots.position_unit(tables.results),
        )
    path = writer.write(output_dir / "report.md")
    log.info("report written to %s and %s", path, write_html(path))
    return path


def compute_comparisons(tables: RunTables, uncertainty: Uncertainty) -> Comparisons:
    """The paired comparisons of the runs' rankings (`Comparisons`); each paradigm and threshold
    that does not separate the ground truths from the baseline is logged as a warning."""
    best_k = best_k_comparisons(tables.query_localized, uncertainty)
    separated = separation(best_k)
    units = dataset_units(tables.results)
    for row in separated[~separated["separates"].astype(bool)].itertuples():
        log.warning(
            "%s on %s at %g %s, %g°: no ground truth is distinguishable from the baseline (%s): this paradigm does "
            "not separate rankings on this scene at this threshold",
            row.paradigm,
            row.dataset,
            row.position_threshold_m,
            units.get(row.dataset, "m"),
            row.rotation_threshold_deg,
            row.pairs,
        )
    return Comparisons(comparison_table(tables.query_localized, uncertainty), best_k, separated, units, uncertainty)


def dataset_units(results: pd.DataFrame) -> dict[str, str]:
    """Each dataset's position unit (`position_unit` of its localization rows)."""
    return results.groupby("dataset")["position_unit"].first().to_dict() if len(results) else {}


def compute_correlations(tables: RunTables) -> Correlations:
    """The three analyses of Sec. 3.7 over the descriptor rankings of ``tables``, the dataset-level
    ones with their dataset's ``position_unit`` (their thresholds' labels)."""
    paired = paired_metrics(tables.retrieval, tables.results)
    units = dataset_units(tables.results)

    def with_units(frame: pd.DataFrame) -> pd.DataFrame:
        return frame.assign(position_unit=frame["dataset"].map(units)) if len(frame) else frame

    return Correlations(
        paired=paired,
        pearson=with_units(dataset_pearson(paired)),
        spearman=with_units(dataset_spearman(paired)),
        query=query_pearson(tables.query_retrieval, tables.query_errors, loosest_threshold(tables.results)),
    )


def loosest_threshold(results: pd.DataFrame) -> tuple[float, float]:
    """The ``(metres, degrees)`` accuracy threshold of ``results`` with the largest position
    threshold (the paper's low accuracy, 5 m and 10 degrees; also the value without results)."""
    if results.empty:
        return (5.0, 10.0)
    row = results.sort_values(["position_threshold_m", "rotation_threshold_deg"]).iloc[-1]
    return float(row["position_threshold_m"]), float(row["rotation_threshold_deg"])


def choose_groundtruth(retrieval: pd.DataFrame, requested: str | None) -> str | None:
    """The ground truth of the correlation analysis (see `build_report`)."""
    available = sorted(retrieval["groundtruth"].unique())
    if requested is not None:
        if requested not in available:
            raise ValueError(f"ground truth {requested!r} is not in the runs' retrieval tables; available: {available}")
        return requested
    preferred = [name for name in available if "relative_pose" in name]
    chosen = (preferred or available or [None])[0]
    if chosen is not None:
        log.info("correlations use ground truth %r (available: %s)", chosen, available)
    return chosen


def overview(
    writer: markdown.ReportWriter, tables: RunTables, groundtruth: str | None, uncertainty: Uncertainty
) -> None:
    results = tables.results
    rankings = pd.concat([results[["ranking", "ranking_kind"]], tables.retrieval[["ranking", "ranking_kind"]]])
    rankings = rankings.drop_duplicates().sort_values(["ranking_kind", "ranking"])
    paradigms = results.groupby("paradigm")["k"].unique()
    writer.bullets(
        {
            "runs": ", ".join(md_code(run) for run in tables.run_dirs),
            "rankings": ", ".join(md_text(f"{r.ranking} ({r.ranking_kind})") for r in rankings.itertuples()) or "none",
            "paradigms": ", ".join(f"{md_text(p)} (k={sorted(int(k) for k in ks)})" for p, ks in paradigms.items())
            or "none",
            "subsets": md_text(", ".join(sorted(set(results["subset"]) | set(tables.retrieval["subset"])))) or "none",
            "ground truth of the correlation analysis": md_text(groundtruth or "none"),
            "uncertainty": md_text(uncertainty_text(results, uncertainty)),
        }
    )
    for number, (run, summary) in enumerate(tables.summaries.items()):
        writer.heading(f"Run {md_code(run)}", 3)
        stages = summary.get(SFM_STAGES)
        writer.bullets(
            {md_text(key): md_text(summary_text(value)) for key, value in summary.items() if key != SFM_STAGES}
        )
        if isinstance(stages, dict) and stages:
            caption = "SfM stages: seconds of work (stages overlap) and work done, in each stage's units."
            writer.table(sfm_stage_table(stages), f"sfm_stages_{number}", caption, ".1f")


def uncertainty_text(results: pd.DataFrame, uncertainty: Uncertainty) -> str:
    """What the intervals are, and what one query is worth, in words."""
    level = f"{100 * uncertainty.confidence:g} %"
    text = (
        f"every figure with its {level} interval over its queries: Wilson's for a share of queries (% localized, "
        f"R@k, % with an estimate), a bootstrap of the queries ({uncertainty.resamples} resamples, seed "
        f"{uncertainty.seed}) for means and medians (P@k, mAP@k, median errors); two rankings are compared on the "
        f"same queries (exact McNemar test, Bonferroni's correction over the pairs of a panel; {COMPARISON_FILE})"
    )
    everyone = results[results["subset"] == "all"] if len(results) else results
    counts = sorted({int(n) for n in everyone["num_queries"]}) if len(everyone) else []
    if counts:
        worth = ", ".join(f"{100 / n:.3g} points of {n} queries" for n in counts)
        text += f"; one query is {worth}"
    return text


def sfm_stage_table(stages: dict) -> pd.DataFrame:
    """One row per SfM stage of a summary's ``stages``: its seconds, work done and unit."""
    rows = {
        str(stage): {
            "seconds": float(record.get("seconds", float("nan"))),
            "work done": int(record.get("done", 0)),
            "unit": str(record.get("unit", "")),
        }
        for stage, record in stages.items()
        if isinstance(record, dict)
    }
    return pd.DataFrame.from_dict(rows, orient="index").rename_axis("stage")


def summary_text(value: object) -> str:
    """A value of a run's summary in words: a mapping (a reconstruction's quality) as
    ``key: value`` pairs, its empty entries left out."""
    if isinstance(value, dict):
        return "; ".join(f"{key}: {item}" for key, item in value.items() if item is not None)
    return str(value)


def groundtruth_section(writer: markdown.ReportWriter, tables: RunTables) -> None:
    statistics = tables.groundtruth_statistics
    if statistics.empty:
        return
    writer.heading("Ground-truth statistics (paper Table 1)")
    caption = "Relevant database images per query (queries with a pose)."
    writer.table(statistics.set_index(["dataset", "groundtruth"]), "table1_groundtruth_statistics", caption)


def localization_section(
    writer: markdown.ReportWriter, tables: RunTables, comparisons: Comparisons, painters: Painters, colors: dict
) -> None:
    results = tables.results
    writer.heading("Localization (paper Figs. 4-6)")
    if results.empty:
        writer.text("No localization results: no query has a reference pose.")
        return
    best = markdown.best_localization(results)
    caption = (
        "Best % of queries localized over k (all queries), its interval and the k where it is reached; the k is "
        "chosen on these queries, so the best figure leans optimistic."
    )
    writer.table(best, "localization_best_over_k", caption)
    difference_section(writer, results, comparisons)
    for (dataset, paradigm, method), _ in results.groupby(["dataset", "paradigm", "method"], sort=True):
        writer.heading(md_text(f"{dataset}: {paradigm}, {method}"), 3)
        rows = results[(results["dataset"] == dataset) & (results["paradigm"] == paradigm)]  # a job per figure
        writer.figures(painters.draw(plots.plot_localization_vs_k, rows, painters.figures, colors, methods=[method]))
        pivot = markdown.pivot_localization(results[results["dataset"] == dataset], paradigm, method)
        caption = "% of queries localized (all queries) with its interval, per ranking and k."
        writer.table(pivot, f"localization_{dataset}_{paradigm}_{method}", caption)


def difference_section(writer: markdown.ReportWriter, results: pd.DataFrame, comparisons: Comparisons) -> None:
    """Which differences of the best-over-k table are real (`Comparisons.best_k`), and each paradigm
    that does not separate the ground truths from the baseline."""
    writer.heading("Which differences are real", 3)
    if comparisons.best_k.empty:
        why = (
            "one ranking only"
            if results["ranking"].nunique() < 2
            else "the runs have no per-query outcomes (query_localized.csv.gz: runs of an earlier version)"
        )
        writer.text(f"No paired comparison: {md_text(why)}.")
        return
    best_k = comparisons.best_k.assign(position_unit=comparisons.best_k["dataset"].map(comparisons.units))
    table = markdown.difference_table(best_k)
    caption = (
        "Paired differences in points (ranking minus other, each at its best k, on the queries both were evaluated "
        "on), with their exact interval given the queries only one of them localized (exact McNemar test), at "
        f"{100 * comparisons.uncertainty.confidence:g} % for all the pairs of a paradigm, method and threshold "
        "together (Bonferroni): better or worse exactly where the interval excludes 0. Every pair at every k is in "
        f"{COMPARISON_FILE}."
    )
    writer.table(table, "localization_differences", caption)
    writer.text(*markdown.separation_lines(comparisons.separation, comparisons.units))


def retrieval_section(writer: markdown.ReportWriter, tables: RunTables, painters: Painters, colors: dict) -> None:
    retrieval = tables.retrieval
    if retrieval.empty:
        return
    writer.heading("Retrieval metrics (paper Figs. 7 and 10)")
    writer.text(
        "P@k: relevant images among the top k / k. R@k: queries with a relevant image in the top k. "
        "mAP@k: AP over the top k normalised by min(#relevant, k), over queries with a relevant image."
    )
    writer.figures(painters.draw(plots.plot_retrieval_curves, retrieval, painters.figures, colors=colors))
    summary = markdown.retrieval_summary(retrieval)
    writer.table(summary, "retrieval_summary", "Retrieval metrics in % (all queries) with their intervals.")


def revisited_section(writer: markdown.ReportWriter, tables: RunTables) -> None:
    if tables.revisited.empty:
        return
    writer.heading("Revisited Oxford and Paris (paper Table 2)")
    writer.table(markdown.revisited_summary(tables.revisited), "table2_revisited", "mAP (%) per protocol.", ".1f")


def correlation_section(
    writer: markdown.ReportWriter,
    tables: RunTables,
    correlations: Correlations,
    groundtruth: str | None,
    painters: Painters,
    colors: dict,
) -> None:
    if groundtruth is None or correlations.pearson.empty:
        return
    writer.heading(
        f"Correlation between retrieval and localization (paper Sec. 3.7), relevance: {md_text(groundtruth)}"
    )
    descriptors = sorted(set(correlations.paired["ranking"])) if len(correlations.paired) else []
    writer.text(
        "Pearson: per descriptor, over k, between the retrieval metric and % localized (Tables 3 and 6). "
        "Spearman: per k, over the descriptors (Tables 4 and 5). Violins: per query, over k, between the "
        "retrieval metric and the negated capped pose error min(1, max(c/tau_c, R/tau_R)) at the loosest "
        "threshold, failures scoring 1 (Figs. 8 and 11). An undefined coefficient says why in its cell (a constant "
        "series, fewer than 2 points, 3 per query); every coefficient is in "
        f"{', '.join(CORRELATION_FILES.values())}."
    )
    if len(descriptors) < 2:
        writer.text(
            f"Spearman's rho over the descriptors needs at least 2 descriptors; these runs have {len(descriptors)} "
            f"({md_text(', '.join(descriptors) or 'none')}): its tables are left out. A report over runs of "
            "several descriptors on this scene (report.py) has them."
        )
    for metric in [m for m in METRIC_TITLES if m in set(correlations.pearson["retrieval_metric"])]:
        pearson, spearman, pairs = (
            _selected(frame, groundtruth, metric)
            for frame in (correlations.pearson, correlations.spearman, correlations.paired)
        )
        query = _selected(correlations.query, groundtruth, METRICS[metric])
        writer.heading(METRIC_TITLES[metric], 3)
        writer.figures(painters.draw(plots.plot_correlation_scatter, pairs, pearson, painters.figures, colors))
        stem = f"{metric}_{groundtruth}"
        writer.table(
            markdown.correlation_matrix(pearson, "ranking"), f"pearson_{stem}", "Pearson r over k, per descriptor."
        )
        if len(descriptors) >= 2:
            caption = "Spearman rho over the descriptors, per k."
            writer.table(markdown.correlation_matrix(spearman, "k"), f"spearman_{stem}", caption)
        if len(query) and query["coefficient"].notna().any():
            writer.figures(painters.draw(plots.plot_query_violins, query, painters.figures, colors))
        elif len(query):
            reasons = markdown.undefined_summary(query)
            why = "; ".join(f"{row.undefined_reason}: {row.count}" for row in reasons.itertuples())
            writer.text(f"No per-query coefficient is defined, so no violin is drawn ({md_text(why)}).")
        analyses = {"pearson": pearson, "per query": query} | ({"spearman": spearman} if len(descriptors) >= 2 else {})
        undefined = pd.concat(
            [markdown.undefined_summary(frame).assign(analysis=name) for name, frame in analyses.items()]
        )
        if len(undefined):
            table = markdown.markdown_table(undefined[["analysis", "undefined_reason", "count"]], index=False)
            writer.text("Undefined coefficients:", table)


def _selected(frame: pd.DataFrame, groundtruth: str, metric: str) -> pd.DataFrame:
    """Rows of one ground truth and retrieval metric, over all queries."""
    rows = frame[(frame["groundtruth"] == groundtruth) & (frame["retrieval_metric"] == metric)]
    return rows[rows["subset"] == "all"] if "subset" in rows else rows


def subset_section(
    writer: markdown.ReportWriter, tables: RunTables, groundtruth: str | None, painters: Painters, colors: dict
) -> None:
    subsets = set(tables.results["subset"]) | set(tables.retrieval["subset"])
    if subsets <= {"all"}:
        return
    writer.heading("Subsets (paper Sec. 4.3, Fig. 12)")
    sizes = markdown.subset_sizes(tables.results, tables.retrieval)
    writer.table(sizes, "subset_sizes", "Queries evaluated per subset.", ".0f")
    if len(tables.subsets):
        per_image = tables.subsets.groupby("dataset").agg(
            images=("image", "size"),
            median_blur_score=("blur_score", "median"),
            median_dynamic_fraction=("dynamic_fraction", "median"),
            mask_source=("mask_source", "first"),
        )
        caption = "Blur scores (FFT, blurry when <= threshold) and dynamic fractions of the queries."
        writer.table(per_image, "subset_scores", caption)
    for subset in sorted(subsets - {"all"}):  # a job each: they are the report's largest figures
        arguments = (tables.results, tables.retrieval, groundtruth, painters.figures, colors)
        writer.figures(painters.draw(plots.plot_subset_comparison, *arguments, subsets=[subset]))
    if len(tables.results):
        best = markdown.best_by_subset(tables.results)
        writer.table(best, "best_by_subset", "Best % localized over k at the loosest threshold.", ".1f")


def failure_section(writer: markdown.ReportWriter, tables: RunTables, uncertainty: Uncertainty) -> None:
    if tables.query_errors.empty:
        return
    writer.heading("Median errors")
    medians = median_errors(tables.query_errors, uncertainty)
    caption = (
        "Median position and rotation errors over the queries with an estimate and a reference pose, and the % of "
        "queries with an estimate, each with its interval (– where no query has an estimate)."
    )
    writer.table(markdown.median_error_summary(medians), "median_errors", caption)
    writer.heading("Failures")
    failures = markdown.failure_summary(tables.query_errors)
    writer.text(
        markdown.markdown_table(failures, index=False) if len(failures) else "Every query received an estimate."
    )
