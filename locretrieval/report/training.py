"""The report of a train.py run, written at its end (`write_training_report`): ``validation.csv``,
``gap.csv`` and ``report.md`` with the validation curves, the gap table and the galleries, written
by the evaluation report's writer (`locretrieval.report.markdown.ReportWriter`: every config or data
string in it escaped)."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from locretrieval.benchmark import BenchmarkSettings
from locretrieval.config import require
from locretrieval.metrics.comparison import gap_closed
from locretrieval.metrics.uncertainty import Uncertainty, share_interval
from locretrieval.report.markdown import ReportWriter, difference_text, interval_text, markdown_table, md_text
from locretrieval.report.training_runs import GAP_COLUMNS, GAP_FILE, VALIDATION_FILE, VALIDATION_QUERIES_FILE
from locretrieval.training.callbacks import HELD_OUT, SELECTION, LocalizationValidation, localization_key


@dataclass
class GapRow:
    """A row of the gap table: ``paradigm``'s ``method`` at ``k``, % of the validation queries
    localized within ``threshold`` ``[metres, degrees]``, closing the gap to the first of
    ``groundtruths`` (ground-truth definitions) that was validated."""

    paradigm: str
    method: str
    k: int
    threshold: list[float]
    groundtruths: list[str]

    def __post_init__(self) -> None:
        require(len(self.threshold) == 2, "threshold", f"must be [metres, degrees], got {self.threshold}")
        require(len(self.groundtruths) >= 1, "groundtruths", "must name at least one ground-truth definition")

    @property
    def key(self) -> str:
        """Its localization key (`callbacks.localization_key`): the metric's name after its prefix."""
        return localization_key(self.paradigm, self.method, self.k, *self.threshold)

    @property
    def metric(self) -> str:
        """Its key in the validation metrics on the queries selected on (`callbacks.metric_rows`)."""
        return f"{SELECTION}/{self.key}"

    def unfilled(self, settings: BenchmarkSettings, groundtruths: Collection[str], sfm_validated: bool) -> str | None:
        """Why a validation cannot fill the row with these settings, or None."""
        sections = settings.paradigms.sections
        if self.paradigm not in sections:
            return f"no paradigm {self.paradigm!r} (paradigms: {list(sections)})"
        section = sections[self.paradigm]
        if not section.enabled:
            return f"paradigms.{self.paradigm}.enabled is false"
        if section.uses_sfm and not sfm_validated:
            return "the SfM paradigms are not validated (callbacks.localization_validation.sfm_every_n_epochs is null)"
        if self.method not in section.method_names():
            return f"{self.paradigm} has no method {self.method!r} (methods: {section.method_names()})"
        if self.k not in section.k:
            return f"k={self.k} is not in paradigms.{self.paradigm}.k {section.k}"
        if [float(value) for value in self.threshold] not in [
            [float(p), float(r)] for p, r in settings.metrics.thresholds
        ]:
            return f"the threshold {self.threshold} is not in metrics.thresholds {settings.metrics.thresholds}"
        if not set(self.groundtruths) & set(groundtruths):
            return f"none of its ground truths {self.groundtruths} is validated (groundtruth: {sorted(groundtruths)})"
        return None


@dataclass
class TrainingReportSettings:
    """The ``report`` section of train.yaml: the ``gap`` rows of the training report and the
    ``baseline`` they measure the gap from (a ``validation_references`` name)."""

    baseline: str
    gap: list[GapRow]

    def metrics(self) -> list[str]:
        """The validation metrics of the gap rows: the report's figure and the console's headline."""
        return [row.metric for row in self.gap]


def gap_table(validation: LocalizationValidation, settings: TrainingReportSettings) -> pd.DataFrame:
    """Per gap row validated before and after training, on the held-out validation queries (all of
    them without a held-out split; ``split``: ``held_out`` or ``all``): % localized untrained (before
    training), trained (its last validation), by the baseline descriptor and by the ground truth, each
    with its interval, the gap from the baseline to the ground truth and the share of it that training closed with their
    intervals (`locretrieval.metrics.comparison.gap_closed`: only where the ground truth beats the
    baseline by a distinguishable margin; ``gap_note`` says why not). `GAP_COLUMNS`."""
    split = HELD_OUT if HELD_OUT in validation.splits else SELECTION
    members = validation.subsets[validation.splits[split]]
    split = validation.splits[split]  # its subset's name: held_out, or all
    uncertainty = validation.settings.metrics.uncertainty
    baseline = settings.baseline
    rows = []
    for row in settings.gap:
        validated = [outcomes[row.key] for outcomes in validation.outcomes if row.key in outcomes]
        if len(validated) < 2:
            continue
        groundtruth = next(
            (
                f"gt_{name}"
                for name in row.groundtruths
                if row.key in validation.reference_outcomes.get(f"gt_{name}", {})
            ),
            None,
        )
        references = validation.reference_outcomes
        outcomes = {
            "untrained": validated[0],
            "trained": validated[-1],
            "baseline": references.get(baseline, {}).get(row.key),
            "groundtruth": references[groundtruth][row.key] if groundtruth else None,
        }
        rows.append(gap_row(row.key, split, members, outcomes, uncertainty, baseline) | {"groundtruth": groundtruth})
    table = pd.DataFrame(rows, columns=GAP_COLUMNS + [baseline])
    return table[GAP_COLUMNS[:7] + [baseline] + GAP_COLUMNS[7:]]


def gap_row(
    key: str,
    split: str,
    members: np.ndarray,
    outcomes: Mapping[str, np.ndarray | None],
    uncertainty: Uncertainty,
    baseline: str,
) -> dict[str, object]:
    """One row of `gap_table` from the per-query ``outcomes`` (int8, -1: not evaluated) of the
    untrained and trained network, the baseline and the ground truth (None: not validated), over
    the queries of ``members`` that all of them evaluated."""
    evaluated = members & np.logical_and.reduce([o >= 0 for o in outcomes.values() if o is not None])
    localized = {name: (o[evaluated] > 0 if o is not None else None) for name, o in outcomes.items()}
    count = int(evaluated.sum())

    def share(name: str) -> tuple[float, float, float]:
        if localized[name] is None or not count:
            return float("nan"), float("nan"), float("nan")
        hits = int(localized[name].sum())
        low, high = share_interval(hits, count, uncertainty.confidence)
        return 100 * hits / count, 100 * float(low), 100 * float(high)

    trained, base, truth = share("trained"), share("baseline"), share("groundtruth")
    row = {
        "metric": key,
        "split": split,
        "num_queries": count,
        "untrained": share("untrained")[0],
        "trained": trained[0],
        "trained_low": trained[1],
        "trained_high": trained[2],
        baseline: base[0],
        "baseline_low": base[1],
        "baseline_high": base[2],
        "groundtruth_value": truth[0],
        "groundtruth_low": truth[1],
        "groundtruth_high": truth[2],
    }
    if localized["baseline"] is None or localized["groundtruth"] is None or not count:
        missing = "no ground truth validated" if localized["groundtruth"] is None else f"no {baseline} value"
        return row | {"gap_note": f"gap undefined: {missing}" if count else "gap undefined: no query evaluated"}
    gap = gap_closed(localized["trained"], localized["baseline"], localized["groundtruth"], uncertainty, baseline)
    return row | {
        "gap_pts": gap.gap,
        "gap_low_pts": gap.gap_low,
        "gap_high_pts": gap.gap_high,
        "gap_closed_pct": gap.closed,
        "gap_closed_low_pct": gap.closed_low,
        "gap_closed_high_pct": gap.closed_high,
        "gap_note": gap.note,
    }


#: The galleries of the training report: ``(key in LocalizationValidation.galleries, file, caption)``.
GALLERIES = (
    ("before", "gallery_before.jpg", "before training"),
    ("last", "gallery_last.jpg", "at the last validation"),
)


def gallery_section(writer: ReportWriter, validation: LocalizationValidation) -> None:
    """Write the validation galleries (`LocalizationValidation.galleries`) into the report's folder
    and show them in its report."""
    from PIL import Image

    for key, file, caption in GALLERIES:
        if key in validation.galleries:
            Image.fromarray(validation.galleries[key]).save(writer.directory / file, quality=85)
            writer.text(
                f"Top {validation.gallery_k} of validation queries {caption} (query first; green: relevant, red: not, "
                f"by the {md_text(validation.gallery_groundtruth)} ground truth):"
            )
            writer.image(f"gallery {caption}", file)


#: The validation queries a gap row is measured on, in words (``gap.csv``'s ``split``).
SPLIT_WORDS = {"held_out": "the held-out validation queries", "all": "all the validation queries"}
#: Line styles of the reference rankings in ``validation.png``: ground truths dashed, the others dotted.
REFERENCE_STYLES = {True: "--", False: ":"}


def write_training_report(
    validation: LocalizationValidation, output_dir: Path, settings: TrainingReportSettings, unfilled: Mapping[str, str]
) -> pd.DataFrame:
    """Write ``validation.csv`` (`VALIDATION_COLUMNS`: each figure of each validation with its interval
    and number of queries; epoch -1 is before training), ``validation_queries.csv.gz`` (each query's
    outcome, `OUTCOME_COLUMNS`) and ``report.md`` (the gap rows' metrics per epoch with their intervals
    against the reference rankings, ``validation.png``, the gap table of `gap_table` (also ``gap.csv``),
    a line per requested row it cannot fill (``unfilled``: metric -> why), the galleries of the fixed
    validation queries before training and at the last validation)."""
    table = validation.history_table()
    table.to_csv(output_dir / VALIDATION_FILE, index=False)
    validation.outcome_table().to_csv(output_dir / VALIDATION_QUERIES_FILE, index=False)
    shown = [
        metric
        for row in settings.gap
        for metric in (row.metric, f"{HELD_OUT}/{row.key}")
        if metric in set(table["metric"])
    ]
    writer = ReportWriter(output_dir, "Training report")
    writer.text(
        f"% of validation queries localized with its {100 * validation.settings.metrics.uncertainty.confidence:g} % "
        f"interval (epoch -1: before training); {md_text(validation.resolution())}."
    )
    if shown:
        rows = table[table["metric"].isin(shown)]
        text = [interval_text(v, lo, hi) for v, lo, hi in zip(rows["value"], rows["low"], rows["high"])]
        wide = rows.assign(text=text).pivot(index="epoch", columns="metric", values="text")[shown]
        writer.text(markdown_table(wide.fillna("not validated"), index=True))
        draw_validation(table, validation, [m for m in shown if m.startswith(f"{SELECTION}/")], output_dir)
        writer.image("validation curves", "validation.png")
    gaps = gap_table(validation, settings)
    gaps.to_csv(output_dir / GAP_FILE, index=False)
    if len(gaps):
        writer.text(
            f"What training bought, per paradigm: % localized on {SPLIT_WORDS[gaps['split'].iloc[0]]}, and "
            f"the share of the gap between {md_text(settings.baseline)} and the ground truth that training closed, "
            "where there is a gap (the ground truth distinguishably above the baseline):",
            markdown_table(gap_markdown(gaps, settings.baseline), index=False),
        )
    writer.text(
        *(
            f"Requested row {md_text(metric.removeprefix(f'{SELECTION}/'))} (report.gap) is not filled: {md_text(why)}."
            for metric, why in unfilled.items()
        )
    )
    references = reference_table(validation, shown)
    if len(references):
        writer.text("Reference rankings:", markdown_table(references))
    gallery_section(writer, validation)
    writer.write(output_dir / "report.md")
    return table


def gap_markdown(gaps: pd.DataFrame, baseline: str) -> pd.DataFrame:
    """The gap table as the report shows it: each figure with its interval, the gap closed or why there is none."""

    def shown(values: pd.DataFrame, value: str, low: str, high: str) -> list[str]:
        return [interval_text(v, lo, hi) for v, lo, hi in zip(values[value], values[low], values[high])]

    closed = [
        note or interval_text(value, low, high)
        for value, low, high, note in zip(
            gaps["gap_closed_pct"], gaps["gap_closed_low_pct"], gaps["gap_closed_high_pct"], gaps["gap_note"].fillna("")
        )
    ]
    return pd.DataFrame(
        {
            "metric": gaps["metric"],
            "queries": gaps["num_queries"],
            "untrained": [f"{value:.1f}" for value in gaps["untrained"]],
            "trained": shown(gaps, "trained", "trained_low", "trained_high"),
            baseline: shown(gaps, baseline, "baseline_low", "baseline_high"),
            "ground truth": [
                f"{name}: {text}" if isinstance(name, str) else "none validated"
                for name, text in zip(
                    gaps["groundtruth"], shown(gaps, "groundtruth_value", "groundtruth_low", "groundtruth_high")
                )
            ],
            "gap (points)": [
                "–" if pd.isna(value) else difference_text(value, low, high, "").strip()
                for value, low, high in zip(gaps["gap_pts"], gaps["gap_low_pts"], gaps["gap_high_pts"])
            ],
            "gap closed (%)": closed,
        }
    )


def reference_table(validation: LocalizationValidation, shown: list[str]) -> pd.DataFrame:
    """The reference rankings' figures of the ``shown`` metrics, with their intervals."""
    cells = {
        name: {
            metric: interval_text(
                values[metric], *validation.reference_details.get(name, {}).get(metric, [np.nan] * 2)[:2]
            )
            for metric in shown
            if metric in values
        }
        for name, values in validation.reference.items()
    }
    return pd.DataFrame(cells).T.fillna("not validated") if any(cells.values()) else pd.DataFrame()


def draw_validation(
    table: pd.DataFrame, validation: LocalizationValidation, metrics: list[str], output_dir: Path
) -> None:
    """``validation.png``: a panel per metric, % localized per epoch with its interval (the queries
    selected on solid, the held-out ones dashed), each reference ranking a horizontal line of its own
    colour with its interval as a band; epochs as whole numbers."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    figure, axes = plt.subplots(1, len(metrics), figsize=(4.8 * len(metrics), 3.4), squeeze=False)
    for axis, metric in zip(axes[0], metrics):
        key = metric.removeprefix(f"{SELECTION}/")
        for name, style, color in ((metric, "-", colors[0]), (f"{HELD_OUT}/{key}", "--", colors[0])):
            rows = table[table["metric"] == name].sort_values("epoch")
            if len(rows):
                label = "trained, held out" if name.startswith(HELD_OUT) else "trained"
                axis.plot(rows["epoch"], rows["value"], style, marker="o", color=color, label=label)
                axis.fill_between(rows["epoch"], rows["low"], rows["high"], color=color, alpha=0.12, linewidth=0)
        for index, (name, values) in enumerate(validation.reference.items(), start=1):
            if metric in values:
                color = colors[index % len(colors)]
                style = REFERENCE_STYLES[name.startswith("gt_")]
                axis.axhline(values[metric], linestyle=style, color=color, label=name)
                low, high = validation.reference_details.get(name, {}).get(metric, [np.nan, np.nan])[:2]
                if np.isfinite(low) and np.isfinite(high):
                    axis.axhspan(low, high, color=color, alpha=0.08, linewidth=0)
        axis.xaxis.set_major_locator(MaxNLocator(integer=True))
        axis.set(title=key, xlabel="epoch", ylabel="% localized", ylim=(-2, 102))
    axes[0][-1].legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(output_dir / "validation.png", dpi=100)
    plt.close(figure)
