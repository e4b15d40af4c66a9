"""The table of what training bought over several train.py runs (their ``gap.csv``): per run and
paradigm, DenseVLAD / untrained / trained / ground truth (% localized), and over all runs the
means and the share of the mean gap closed, ``(trained - densevlad) / (groundtruth - densevlad)``.

    python scripts/gap_table.py outputs/train/... [more runs]     # prints Markdown
"""

import argparse
from pathlib import Path

import pandas as pd

from locretrieval.training.report import GAP_BASELINE


def load(runs: list[Path]) -> pd.DataFrame:
    """Every run's ``gap.csv`` with a ``run`` column (the folder name)."""
    tables = [pd.read_csv(run / "gap.csv").assign(run=run.name) for run in runs]
    return pd.concat(tables, ignore_index=True)


def markdown(table: pd.DataFrame) -> str:
    """One row per run and paradigm metric, then the mean over runs per metric with its gap closed."""
    columns = [GAP_BASELINE, "untrained", "trained", "groundtruth_value"]
    means = table.groupby("metric", sort=False)[columns].mean().reset_index().assign(run="mean")
    means["gap_closed_pct"] = 100 * (means["trained"] - means[GAP_BASELINE]) / (means["groundtruth_value"] - means[GAP_BASELINE])
    means["groundtruth"] = table.groupby("metric", sort=False)["groundtruth"].first().values
    shown = pd.concat([table, means], ignore_index=True)[["metric", "run", *columns, "groundtruth", "gap_closed_pct"]]
    shown = shown.sort_values(["metric", "run"], key=lambda column: column.map(lambda value: (value == "mean", value)))
    return shown.to_markdown(index=False, floatfmt=".1f")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    print(markdown(load(parser.parse_args().runs)))


if __name__ == "__main__":
    main()
