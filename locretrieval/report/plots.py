"""Figures drawn from the tidy result tables only (no recomputation), as PNG and/or PDF.

Descriptor rankings are solid lines, ground-truth rankings dashed (the upper bounds of
paper Figs. 4-6) and baselines dotted; a ranking keeps its colour in every figure. A curve of
figures over queries (% localized, P@k, R@k, mAP@k) carries its interval as a light band of its colour.

matplotlib is imported by the first figure drawn (`pyplot`), not with this module: a run
without figures (``report.figure_formats=[]``) does not load it.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from locretrieval.cache import safe_name
from locretrieval.metrics.comparison import REFERENCE_METHOD
from locretrieval.scene.types import METRES

if TYPE_CHECKING:
    import matplotlib.pyplot as plt

#: Colours of the rankings: matplotlib's default cycle ("tab10"), named here so that the process
#: writing the report assigns them without importing matplotlib (its workers draw).
RANKING_COLORS = (
    "#1f77b4",
    "#ff7f0e",
    "#2ca02c",
    "#d62728",
    "#9467bd",
    "#8c564b",
    "#e377c2",
    "#7f7f7f",
    "#bcbd22",
    "#17becf",
)
#: Line style per ranking kind: descriptors solid, ground truth dashed (paper Fig. 4).
LINE_STYLES = {"descriptor": "-", "groundtruth": "--", "baseline": ":"}
#: The opacity of an interval's band.
BAND_ALPHA = 0.12
METRIC_LABELS = {"precision": "P@k", "recall": "R@k", "map": "mAP@k", "average_precision": "AP@k"}  # AP: per query
PANEL_WIDTH, PANEL_HEIGHT = 4.2, 3.6
#: The widest a figure is drawn, in inches: three panels, shown at about their size on a report page.
FIGURE_WIDTH_INCHES = 13.0
#: Room in inches around and between the panels, for the text every panel has: tick labels of at
#: most four characters, one-line axis labels and titles (two-line 7-point tick labels under the
#: violins, which have no x label), the figure's one-line title; legends are inside the axes.
#: Fixed rather than a tight layout, which measures every text with a draw of its own.
MARGINS_INCHES = {"left": 0.8, "right": 0.2, "bottom": 0.6, "top": 0.75, "between": 0.9}
#: Width in inches allowed per character of a 7-point tick label (0.65 em: above DejaVu Sans's mean).
SMALL_CHARACTER_INCHES = 7 * 0.65 / 72
#: `savefig` options per file suffix: PNG at zlib's fastest level (measured: 40 % less encoding time, 5 % larger files).
SAVE_OPTIONS = {".png": {"pil_kwargs": {"compress_level": 1}}}
PERCENT_LIMITS = (-2, 102)  # a little room around 0 and 100 %
#: The columns of a localization row's interval, and of a retrieval row's (in %, `plot_retrieval_curves`).
LOCALIZED_BAND = ("localized_low_pct", "localized_high_pct")
PERCENT_BAND = ("low_percent", "high_percent")
THRESHOLD_COLUMNS = ["position_threshold_m", "rotation_threshold_deg"]
#: One correlation figure per dataset x ground truth x retrieval metric.
FIGURE_KEYS = ["dataset", "groundtruth", "retrieval_metric"]


@functools.cache
def pyplot():
    """``matplotlib.pyplot`` on the non-interactive Agg backend (chosen once, on first use); text is
    drawn as written (no ``$...$`` math: a ``$`` in a ranking or dataset name is a character)."""
    import matplotlib

    matplotlib.use("Agg")
    matplotlib.rcParams["text.parse_math"] = False
    import matplotlib.pyplot

    return matplotlib.pyplot


def ranking_colors(names: Iterable[str]) -> dict[str, str]:
    """A stable colour per ranking name (sorted names over `RANKING_COLORS`)."""
    return {name: RANKING_COLORS[n % len(RANKING_COLORS)] for n, name in enumerate(sorted(set(names)))}


@dataclass(frozen=True)
class FigureFolder:
    """Where figures go and in which formats (``png``, ``pdf``, ...); the first is linked in reports."""

    path: Path
    formats: tuple[str, ...] = ("png", "pdf")

    def save(self, figure: plt.Figure, stem: str) -> Path:
        """Write the figure once per format (name made `safe_name`), one draw each (`_panels`
        fixes the layout); returns the first file."""
        self.path.mkdir(parents=True, exist_ok=True)
        written = [self.path / f"{safe_name(stem)}.{suffix}" for suffix in self.formats]
        for file in written:
            figure.savefig(file, dpi=110, **SAVE_OPTIONS.get(file.suffix, {}))
        pyplot().close(figure)
        return written[0]


def _panels(count: int, panel_width: float = PANEL_WIDTH) -> tuple[plt.Figure, np.ndarray]:
    """A figure of ``count`` panels, in rows of as many as `FIGURE_WIDTH_INCHES` holds (a report
    page shows it at about its size: panels in one long row would be shrunk past reading), with
    `MARGINS_INCHES` around and between them (each row its titles above and labels below)."""
    columns = max(1, min(count, int(FIGURE_WIDTH_INCHES // panel_width)))
    rows = -(-count // columns)
    width, height = panel_width * columns, PANEL_HEIGHT * rows
    margins = MARGINS_INCHES
    axis_width = (width - margins["left"] - margins["right"] - (columns - 1) * margins["between"]) / columns
    axis_height = PANEL_HEIGHT - margins["top"] - margins["bottom"]
    layout = {
        "left": margins["left"] / width,
        "right": 1 - margins["right"] / width,
        "bottom": margins["bottom"] / height,
        "top": 1 - margins["top"] / height,
        "wspace": margins["between"] / axis_width,
        "hspace": (margins["top"] + margins["bottom"]) / axis_height,
    }
    # Titles sit at the top of their axes: auto-placing them above tick labels re-measures every
    # tick label at each draw, and no panel has ticks or (without offsets) an offset text at its top.
    with pyplot().rc_context({"axes.titley": 1.0, "axes.formatter.useoffset": False}):
        figure, axes = pyplot().subplots(rows, columns, figsize=(width, height), squeeze=False, gridspec_kw=layout)
    for unused in axes.ravel()[count:]:
        unused.remove()
    return figure, axes.ravel()[:count]


def threshold_label(position: float, rotation: float, unit: str = METRES) -> str:
    """``0.25 m, 2°``; a scene without a metric scale names its ``unit`` (``0.25 model units, 2°``)."""
    return f"{position:g} {unit}, {rotation:g}°"


def position_unit(rows: pd.DataFrame) -> str:
    """The unit of the position thresholds of ``rows`` (their ``position_unit``; metres for a run of
    an earlier version, which has no such column)."""
    if "position_unit" in rows and len(rows):
        return str(rows["position_unit"].iloc[0])
    return METRES


def headline_threshold(results: pd.DataFrame, paradigm: str) -> tuple[float, float]:
    """The threshold the paper shows for a paradigm: the loosest for pose approximation
    (Fig. 4, "low accuracy"), the tightest for the SfM paradigms (Figs. 5-6, "high")."""
    thresholds = results.loc[results["paradigm"] == paradigm, THRESHOLD_COLUMNS]
    ordered = thresholds.drop_duplicates().sort_values(THRESHOLD_COLUMNS)
    row = ordered.iloc[-1] if paradigm == "approximation" else ordered.iloc[0]
    return float(row["position_threshold_m"]), float(row["rotation_threshold_deg"])


def at_headline_thresholds(results: pd.DataFrame) -> pd.DataFrame:
    """Rows of each paradigm at its `headline_threshold`."""
    keep = np.zeros(len(results), dtype=bool)
    for paradigm in results["paradigm"].unique():
        position, rotation = headline_threshold(results, paradigm)
        keep |= (
            (results["paradigm"] == paradigm)
            & (results["position_threshold_m"] == position)
            & (results["rotation_threshold_deg"] == rotation)
        ).to_numpy()
    return results[keep]


def curves_for_method(table: pd.DataFrame, paradigm: str, method: str) -> pd.DataFrame:
    """Rows to draw for one paradigm/method panel.

    Rankings that have ``method`` use it; rankings without it (ground truth in pose
    approximation, where BDI/CSI need descriptors) are drawn with EWB, as in the paper.
    """
    rows = table[table["paradigm"] == paradigm]
    own = rows[rows["method"] == method]
    fallback = rows[(rows["method"] == REFERENCE_METHOD) & ~rows["ranking"].isin(own["ranking"])]
    return pd.concat([own, fallback])


def _log_k_axis(axis: plt.Axes, ks: Iterable[int]) -> None:
    """Logarithmic k axis labelled with the k values drawn (1, 2, 5, 10, ... when there are many)."""
    from matplotlib import ticker

    ks = sorted({int(k) for k in ks})
    nice = [m * 10**e for e in range(4) for m in (1, 2, 5) if ks[0] <= m * 10**e <= ks[-1]]
    axis.set_xscale("log")
    axis.set_xticks(ks if len(ks) <= 10 else nice, minor=False)
    axis.xaxis.set_major_formatter(ticker.ScalarFormatter())
    axis.xaxis.set_minor_locator(ticker.NullLocator())
    axis.set_xlabel("k (retrieved images)")


def _line(
    axis: plt.Axes,
    rows: pd.DataFrame,
    x: str,
    y: str,
    label: str,
    kind: str,
    color: str,
    style: str | None = None,
    band: tuple[str, str] | None = None,
) -> None:
    """One curve; markers only on short curves, where they do not hide the dashes; with ``band``
    (the columns of an interval's ends) the interval as a light band, where it is known."""
    rows = rows.sort_values(x)
    marker = "o" if len(rows) <= 15 else None
    axis.plot(
        rows[x], rows[y], style or LINE_STYLES.get(kind, "-"), color=color, marker=marker, markersize=3, label=label
    )
    if band is not None and set(band) <= set(rows.columns) and rows[list(band)].notna().all(axis=None):
        axis.fill_between(rows[x], rows[band[0]], rows[band[1]], color=color, alpha=BAND_ALPHA, linewidth=0)


def plot_localization_vs_k(
    table: pd.DataFrame, figures: FigureFolder, colors: Mapping[str, str], methods: Iterable[str] | None = None
) -> list[Path]:
    """One figure per dataset x paradigm x method (those in ``methods``, default all): %
    localised vs k over all queries with its interval, a panel per threshold (paper Figs. 4-6),
    ground truth dashed."""
    table = table[table["subset"] == "all"]
    written = []
    for (dataset, paradigm), rows in table.groupby(["dataset", "paradigm"], sort=True):
        drawn = set(rows["method"]) if methods is None else set(rows["method"]) & set(methods)
        for method in sorted(drawn):
            curves = curves_for_method(rows, paradigm, method)
            thresholds = curves[THRESHOLD_COLUMNS].drop_duplicates().sort_values(THRESHOLD_COLUMNS)
            figure, axes = _panels(len(thresholds))
            for axis, (position, rotation) in zip(axes, thresholds.itertuples(index=False)):
                at = curves[
                    (curves["position_threshold_m"] == position) & (curves["rotation_threshold_deg"] == rotation)
                ]
                for (ranking, kind, used), line in at.groupby(["ranking", "ranking_kind", "method"], sort=True):
                    label = f"{ranking} ({used})"
                    _line(axis, line, "k", "localized_pct", label, kind, colors[ranking], band=LOCALIZED_BAND)
                _log_k_axis(axis, at["k"])
                title = threshold_label(position, rotation, position_unit(at))
                axis.set(
                    ylabel=f"% localized ({int(at['num_queries'].max())} queries)", ylim=PERCENT_LIMITS, title=title
                )
                axis.grid(True, alpha=0.3)
            axes[-1].legend(fontsize=7, loc="best")
            figure.suptitle(f"{dataset}: {paradigm}, {method}")
            written.append(figures.save(figure, f"{dataset}_{paradigm}_{method}"))
    return written


def plot_retrieval_curves(retrieval: pd.DataFrame, figures: FigureFolder, colors: Mapping[str, str]) -> list[Path]:
    """One figure per dataset x metric: P@k (Fig. 7), R@k (Fig. 10) or mAP@k vs k in %, over
    all queries, a panel per ground truth, every ranking a line with its interval."""
    retrieval = retrieval[retrieval["subset"] == "all"]
    written = []
    for (dataset, metric), rows in retrieval.groupby(["dataset", "metric"], sort=True):
        groundtruths = sorted(rows["groundtruth"].unique())
        figure, axes = _panels(len(groundtruths))
        for axis, groundtruth in zip(axes, groundtruths):
            curves = rows[rows["groundtruth"] == groundtruth]
            for (ranking, kind), line in curves.groupby(["ranking", "ranking_kind"], sort=True):
                _line(axis, in_percent(line), "k", "percent", ranking, kind, colors[ranking], band=PERCENT_BAND)
            axis.set(
                xlabel="k (retrieved images)",
                ylabel=f"{METRIC_LABELS.get(metric, metric)} (%)",
                ylim=PERCENT_LIMITS,
                title=f"relevance: {groundtruth}",
            )
            axis.grid(True, alpha=0.3)
        axes[-1].legend(fontsize=7, loc="best")
        figure.suptitle(f"{dataset}: {METRIC_LABELS.get(metric, metric)}")
        written.append(figures.save(figure, f"{dataset}_{metric}_at_k"))
    return written


def in_percent(rows: pd.DataFrame) -> pd.DataFrame:
    """Retrieval rows with their value and interval in % (``percent``, `PERCENT_BAND`)."""
    percent = {"percent": 100 * rows["value"]}
    if {"value_low", "value_high"} <= set(rows.columns):
        percent |= {PERCENT_BAND[0]: 100 * rows["value_low"], PERCENT_BAND[1]: 100 * rows["value_high"]}
    return rows.assign(**percent)


def plot_correlation_scatter(
    paired: pd.DataFrame, pearson: pd.DataFrame, figures: FigureFolder, colors: Mapping[str, str]
) -> list[Path]:
    """Retrieval metric vs % localised, a point per descriptor and k and a least-squares line
    per descriptor (paper Figs. 8-9): one figure per dataset x ground truth x metric, a
    panel per paradigm/method at its headline threshold.

    ``paired`` holds retrieval rows joined with localisation rows (columns of both tables,
    ``retrieval_metric``/``retrieval_value``); ``pearson`` the matching `dataset_pearson` rows.
    """
    written = []
    keys = ["dataset", "groundtruth", "retrieval_metric", "paradigm", "method", *THRESHOLD_COLUMNS, "ranking"]
    coefficients = pearson.set_index(keys)["coefficient"]
    for (dataset, groundtruth, metric), rows in paired.groupby(FIGURE_KEYS, sort=True):
        rows = at_headline_thresholds(rows)
        panels = sorted(rows.groupby(["paradigm", "method"]).groups)
        figure, axes = _panels(len(panels))
        for axis, (paradigm, method) in zip(axes, panels):
            panel = rows[(rows["paradigm"] == paradigm) & (rows["method"] == method)]
            position, rotation = panel[THRESHOLD_COLUMNS].iloc[0]
            for ranking, points in panel.groupby("ranking", sort=True):
                x, y = 100 * points["retrieval_value"].to_numpy(), points["localized_pct"].to_numpy()
                r = coefficients.get(
                    (dataset, groundtruth, metric, paradigm, method, position, rotation, ranking), np.nan
                )
                axis.scatter(x, y, s=14, color=colors[ranking], label=f"{ranking} (r={r:.2f})")
                if np.ptp(x) > 0:
                    slope, intercept = np.polyfit(x, y, 1)
                    ends = np.array([x.min(), x.max()])
                    axis.plot(ends, slope * ends + intercept, "-", color=colors[ranking], linewidth=1)
            axis.set(
                xlabel=f"{METRIC_LABELS.get(metric, metric)} (%)",
                ylabel="% localized",
                title=f"{paradigm}, {method} ({threshold_label(position, rotation, position_unit(panel))})",
            )
            axis.grid(True, alpha=0.3)
            axis.legend(fontsize=7, loc="best")
        figure.suptitle(f"{dataset}: {METRIC_LABELS.get(metric, metric)} ({groundtruth}) vs localization")
        written.append(figures.save(figure, f"{dataset}_scatter_{metric}_{groundtruth}"))
    return written


def plot_query_violins(query_pearson: pd.DataFrame, figures: FigureFolder, colors: Mapping[str, str]) -> list[Path]:
    """Distribution of per-query Pearson coefficients (paper Figs. 8 and 11 violins): one
    figure per dataset x ground truth x metric, a panel per paradigm/method, a violin per
    descriptor; queries with an undefined coefficient are counted under the axis."""
    written = []
    for (dataset, groundtruth, metric), rows in query_pearson.groupby(FIGURE_KEYS, sort=True):
        panels = sorted(rows.groupby(["paradigm", "method"]).groups)
        names = rows["ranking"].unique()
        slot = SMALL_CHARACTER_INCHES * max(12, *(len(name) for name in names)) + 0.1  # a violin's label
        figure, axes = _panels(len(panels), max(PANEL_WIDTH, MARGINS_INCHES["between"] + len(names) * slot))
        for axis, (paradigm, method) in zip(axes, panels):
            panel = rows[(rows["paradigm"] == paradigm) & (rows["method"] == method)]
            rankings = sorted(panel["ranking"].unique())
            labels = []
            for position, ranking in enumerate(rankings, start=1):
                values = panel.loc[panel["ranking"] == ranking, "coefficient"]
                defined = values.dropna().to_numpy()
                labels.append(f"{ranking}\n{len(defined)}/{len(values)} def.")
                if len(defined) > 1 and np.ptp(defined) > 0:
                    parts = axis.violinplot(defined, positions=[position], showmedians=True)
                    for body in parts["bodies"]:
                        body.set_facecolor(colors[ranking])
                    for lines in ("cbars", "cmins", "cmaxes", "cmedians"):  # else the colour cycle's
                        parts[lines].set_color(colors[ranking])
                elif len(defined):
                    axis.scatter(np.full(len(defined), position), defined, color=colors[ranking], s=10)
            axis.set_xticks(range(1, len(rankings) + 1), labels, fontsize=7)
            axis.set(
                xlim=(0.5, len(rankings) + 0.5),
                ylim=(-1.05, 1.05),
                ylabel="per-query Pearson r",
                title=f"{paradigm}, {method}",
            )
            axis.grid(True, axis="y", alpha=0.3)
        figure.suptitle(f"{dataset}: per-query {METRIC_LABELS.get(metric, metric)} ({groundtruth}) vs -pose error")
        written.append(figures.save(figure, f"{dataset}_violin_{metric}_{groundtruth}"))
    return written


def plot_subset_comparison(
    results: pd.DataFrame,
    retrieval: pd.DataFrame,
    groundtruth: str | None,
    figures: FigureFolder,
    colors: Mapping[str, str],
    subsets: Iterable[str] | None = None,
) -> list[Path]:
    """All queries (solid) vs a subset (dashed) for every descriptor (paper Fig. 12): one
    figure per dataset x subset (those named in ``subsets``, default all), panels for %
    localised per paradigm/method at its headline threshold, then P@k and R@k against
    ``groundtruth``."""
    results = at_headline_thresholds(results[results["ranking_kind"] == "descriptor"])
    retrieval = retrieval[(retrieval["ranking_kind"] == "descriptor") & (retrieval["groundtruth"] == groundtruth)]
    retrieval = in_percent(retrieval[retrieval["metric"].isin(["precision", "recall"])])
    written = []
    for dataset in sorted(set(results["dataset"]) | set(retrieval["dataset"])):
        localization = results[results["dataset"] == dataset]
        ranked = retrieval[retrieval["dataset"] == dataset]
        present = sorted((set(localization["subset"]) | set(ranked["subset"])) - {"all"})
        chosen = [subset for subset in present if subsets is None or subset in set(subsets)]
        panels = [("localization", key) for key in sorted(localization.groupby(["paradigm", "method"]).groups)]
        panels += [("retrieval", metric) for metric in sorted(ranked["metric"].unique())]
        for subset in chosen if panels else []:
            figure, axes = _panels(len(panels))
            for axis, (source, key) in zip(axes, panels):
                if source == "localization":
                    rows = localization[(localization["paradigm"] == key[0]) & (localization["method"] == key[1])]
                    y, ylabel = "localized_pct", "% localized"
                    position, rotation = rows[THRESHOLD_COLUMNS].iloc[0]
                    title = f"{key[0]}, {key[1]} ({threshold_label(position, rotation, position_unit(rows))})"
                else:
                    rows = ranked[ranked["metric"] == key]
                    y, ylabel, title = "percent", f"{METRIC_LABELS[key]} (%)", f"{METRIC_LABELS[key]} ({groundtruth})"
                for ranking, line in rows.groupby("ranking", sort=True):
                    for members, style in (("all", "-"), (subset, "--")):
                        part = line[line["subset"] == members]
                        if len(part):
                            count = int(part["num_queries"].iloc[0])
                            _line(
                                axis,
                                part,
                                "k",
                                y,
                                f"{ranking} {members} ({count})",
                                "descriptor",
                                colors[ranking],
                                style,
                            )
                _log_k_axis(axis, rows["k"])
                axis.set(ylabel=ylabel, ylim=PERCENT_LIMITS, title=title)
                axis.grid(True, alpha=0.3)
                axis.legend(fontsize=7, loc="best")
            figure.suptitle(f"{dataset}: all queries (solid) vs {subset} (dashed)")
            written.append(figures.save(figure, f"{dataset}_subset_{subset}"))
    return written
