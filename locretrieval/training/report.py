"""The training run's validation curves: ``validation.csv`` and ``report.md`` with one figure."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from locretrieval.training.callbacks import HEADLINE, LocalizationValidation


def write_training_report(validation: LocalizationValidation, output_dir: Path) -> pd.DataFrame:
    """Write ``validation.csv`` (epoch, metric, value; epoch -1 is before training) and
    ``report.md`` (headline metrics per epoch against the reference rankings, a figure)."""
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
    references = {name: {m: v for m, v in metrics.items() if m in shown} for name, metrics in validation.reference.items()}
    if references:
        lines += ["Reference rankings:", "", pd.DataFrame(references).T.to_markdown(floatfmt=".3g"), ""]
    (output_dir / "report.md").write_text("\n".join(lines))
    return table
