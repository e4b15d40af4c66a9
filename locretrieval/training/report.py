"""The training run's validation curves: ``validation.csv`` and ``report.md`` with one figure (every
config or data string in it escaped as the evaluation report's, `locretrieval.report.markdown`)."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from locretrieval.benchmark import BenchmarkSettings
from locretrieval.config import require
from locretrieval.report.markdown import markdown_table, md_text
from locretrieval.training.callbacks import LocalizationValidation


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
    def metric(self) -> str:
        """Its key in the validation metrics (`callbacks.metric_rows`)."""
        return f"val/{self.paradigm}/{self.method}/k{self.k}/{self.threshold[0]:g}m_{self.threshold[1]:g}deg"

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
    """Per gap row validated before and after training: untrained (before training), trained
    (its last validation), the baseline descriptor, the ground truth, and the share of the gap
    between baseline and ground truth that training closed, ``100 (trained - baseline) /
    (groundtruth - baseline)`` (% localized; NaN without a baseline or ground truth)."""
    history = validation.history_table()
    baseline = settings.baseline
    rows = []
    for row in settings.gap:
        values = history[history["metric"] == row.metric].sort_values("epoch")
        if len(values) < 2:
            continue
        groundtruth = next(
            (f"gt_{name}" for name in row.groundtruths if row.metric in validation.reference.get(f"gt_{name}", {})),
            None,
        )
        truth = validation.reference[groundtruth][row.metric] if groundtruth else float("nan")
        reference = validation.reference.get(baseline, {}).get(row.metric, float("nan"))
        trained = float(values["value"].iloc[-1])
        rows.append(
            {
                "metric": row.metric.removeprefix("val/"),
                "untrained": float(values["value"].iloc[0]),
                "trained": trained,
                baseline: reference,
                "groundtruth": groundtruth,
                "groundtruth_value": truth,
                "gap_closed_pct": 100.0 * (trained - reference) / (truth - reference)
                if truth != reference
                else float("nan"),
            }
        )
    return pd.DataFrame(
        rows, columns=["metric", "untrained", "trained", baseline, "groundtruth", "groundtruth_value", "gap_closed_pct"]
    )


#: The galleries of the training report: ``(key in LocalizationValidation.galleries, file, caption)``.
GALLERIES = (
    ("before", "gallery_before.jpg", "before training"),
    ("last", "gallery_last.jpg", "at the last validation"),
)


def gallery_lines(validation: LocalizationValidation, output_dir: Path) -> list[str]:
    """Write the validation galleries (`LocalizationValidation.galleries`) and the report lines showing them."""
    from PIL import Image

    lines = []
    for key, file, caption in GALLERIES:
        if key in validation.galleries:
            Image.fromarray(validation.galleries[key]).save(output_dir / file, quality=85)
            lines += [
                f"Top {validation.gallery_k} of validation queries {caption} (query first; green: relevant, red: not, "
                f"by the {md_text(validation.gallery_groundtruth)} ground truth):",
                "",
                f"![gallery {caption}]({file})",
                "",
            ]
    return lines


def write_training_report(
    validation: LocalizationValidation, output_dir: Path, settings: TrainingReportSettings, unfilled: Mapping[str, str]
) -> pd.DataFrame:
    """Write ``validation.csv`` (epoch, metric, value; epoch -1 is before training) and
    ``report.md`` (the gap rows' metrics per epoch against the reference rankings, a figure, the
    gap table of `gap_table` (also ``gap.csv``), a line per requested row it cannot fill
    (``unfilled``: metric -> why), the galleries of the fixed validation queries before training
    and at the last validation)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = validation.history_table()
    table.to_csv(output_dir / "validation.csv", index=False)
    wide = table.pivot(index="epoch", columns="metric", values="value")
    shown = [m for m in settings.metrics() if m in wide.columns]
    lines = ["# Training report", "", "% of validation queries localized (epoch -1: before training).", ""]
    if shown:
        lines += [markdown_table(wide[shown].rename(columns=lambda m: m.removeprefix("val/")), floatfmt=".3g"), ""]
        figure, axes = plt.subplots(1, len(shown), figsize=(4.5 * len(shown), 3.2), squeeze=False)
        for axis, metric in zip(axes[0], shown):
            series = wide[metric].dropna()
            axis.plot(series.index, series.values, marker="o", label="trained")
            for name, reference in validation.reference.items():
                if metric in reference:
                    axis.axhline(reference[metric], linestyle="--" if name.startswith("gt_") else ":", label=name)
            axis.set(title=metric.removeprefix("val/"), xlabel="epoch", ylabel="% localized")
        axes[0][-1].legend(fontsize=7)
        figure.tight_layout()
        figure.savefig(output_dir / "validation.png", dpi=100)
        plt.close(figure)
        lines += ["![validation curves](validation.png)", ""]
    gaps = gap_table(validation, settings)
    gaps.to_csv(output_dir / "gap.csv", index=False)
    if len(gaps):
        lines += [
            f"What training bought, per paradigm (% localized; "
            f"the share of the gap between {md_text(settings.baseline)} and the "
            "ground truth that training closed):",
            "",
            markdown_table(gaps, index=False, floatfmt=".3g"),
            "",
        ]
    lines += [
        f"Requested row {md_text(metric.removeprefix('val/'))} (report.gap) is not filled: {md_text(why)}."
        for metric, why in unfilled.items()
    ]
    lines += [""] if unfilled else []
    references = {
        name: {m: v for m, v in metrics.items() if m in shown} for name, metrics in validation.reference.items()
    }
    if references:
        lines += ["Reference rankings:", "", markdown_table(pd.DataFrame(references).T, floatfmt=".3g"), ""]
    lines += gallery_lines(validation, output_dir)
    (output_dir / "report.md").write_text("\n".join(lines))
    return table
