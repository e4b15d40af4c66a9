"""The training run's validation curves: ``validation.csv`` and ``report.md`` with one figure."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from locretrieval.training.callbacks import HEADLINE, LocalizationValidation


#: Per paradigm, the metric of the gap table and the ground truth closing it (the first present).
GAP_METRICS = {
    "val/approximation/ewb/k3/5m_10deg": ("gt_relative_pose",),
    "val/local_sfm/pnp/k10/0.25m_2deg": ("gt_co_observation", "gt_relative_pose"),
    "val/global_sfm/pnp/k5/0.25m_2deg": ("gt_relative_pose",),
}
#: The reference descriptor the gap is measured from (`LocalizationValidation.reference_models`).
GAP_BASELINE = "densevlad"


def gap_table(validation: LocalizationValidation) -> pd.DataFrame:
    """Per `GAP_METRICS` metric validated before and after training: untrained (before training),
    trained (its last validation), the baseline descriptor, the ground truth, and the share of
    the gap between baseline and ground truth that training closed, ``100 (trained - baseline) /
    (groundtruth - baseline)`` (% localized; NaN without a baseline or ground truth)."""
    history = validation.history_table()
    rows = []
    for metric, groundtruths in GAP_METRICS.items():
        values = history[history["metric"] == metric].sort_values("epoch")
        if len(values) < 2:
            continue
        groundtruth = next((name for name in groundtruths if metric in validation.reference.get(name, {})), None)
        truth = validation.reference[groundtruth][metric] if groundtruth else float("nan")
        baseline = validation.reference.get(GAP_BASELINE, {}).get(metric, float("nan"))
        trained = float(values["value"].iloc[-1])
        rows.append({"metric": metric.removeprefix("val/"), "untrained": float(values["value"].iloc[0]), "trained": trained,
                     GAP_BASELINE: baseline, "groundtruth": groundtruth, "groundtruth_value": truth,
                     "gap_closed_pct": 100.0 * (trained - baseline) / (truth - baseline) if truth != baseline else float("nan")})
    return pd.DataFrame(rows, columns=["metric", "untrained", "trained", GAP_BASELINE, "groundtruth", "groundtruth_value", "gap_closed_pct"])


#: The galleries of the training report: ``(key in LocalizationValidation.galleries, file, caption)``.
GALLERIES = (("before", "gallery_before.jpg", "before training"), ("last", "gallery_last.jpg", "at the last validation"))


def gallery_lines(validation: LocalizationValidation, output_dir: Path) -> list[str]:
    """Write the validation galleries (`LocalizationValidation.galleries`) and the report lines showing them."""
    from PIL import Image

    lines = []
    for key, file, caption in GALLERIES:
        if key in validation.galleries:
            Image.fromarray(validation.galleries[key]).save(output_dir / file, quality=85)
            lines += [f"Top {validation.gallery_k} of validation queries {caption} (query first; green: relevant, red: not, "
                      f"by the {validation.gallery_groundtruth} ground truth):", "", f"![gallery {caption}]({file})", ""]
    return lines


def write_training_report(validation: LocalizationValidation, output_dir: Path) -> pd.DataFrame:
    """Write ``validation.csv`` (epoch, metric, value; epoch -1 is before training) and
    ``report.md`` (headline metrics per epoch against the reference rankings, a figure, the gap
    table of `gap_table` (also ``gap.csv``), the
    galleries of the fixed validation queries before training and at the last validation)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table = validation.history_table()
    table.to_csv(output_dir / "validation.csv", index=False)
    wide = table.pivot(index="epoch", columns="metric", values="value")
    shown = [m for m in HEADLINE if m in wide.columns]
    lines = ["# Training report", "", "% of validation queries localized (epoch -1: before training).", ""]
    if shown:
        lines += [wide[shown].rename(columns=lambda m: m.removeprefix("val/")).to_markdown(floatfmt=".3g"), ""]
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
    gaps = gap_table(validation)
    gaps.to_csv(output_dir / "gap.csv", index=False)
    if len(gaps):
        lines += [f"What training bought, per paradigm (% localized; the share of the gap between {GAP_BASELINE} and the ground "
                  "truth that training closed):", "", gaps.to_markdown(index=False, floatfmt=".3g"), ""]
    references = {name: {m: v for m, v in metrics.items() if m in shown} for name, metrics in validation.reference.items()}
    if references:
        lines += ["Reference rankings:", "", pd.DataFrame(references).T.to_markdown(floatfmt=".3g"), ""]
    lines += gallery_lines(validation, output_dir)
    (output_dir / "report.md").write_text("\n".join(lines))
    return table
