"""The table of what training bought over several train.py runs (their ``gap.csv``): per run and
paradigm, the baseline (``report.baseline``, DenseVLAD by default) / untrained / trained / ground
truth (% localized), and over all runs the means and the share of the mean gap closed,
``(trained - baseline) / (groundtruth - baseline)``.

    python scripts/gap_table.py outputs/train/... [more runs]     # prints Markdown
    python scripts/gap_table.py --wide ...   # one row per run, a cell
                                             # "DenseVLAD / untrained / trained / GT (gap %)" per paradigm
"""

import argparse
from pathlib import Path

import pandas as pd

#: The columns of ``gap.csv`` besides the baseline's (named after it: ``report.baseline``).
COLUMNS = ("metric", "untrained", "trained", "groundtruth", "groundtruth_value", "gap_closed_pct", "run")


def load(runs: list[Path]) -> pd.DataFrame:
    """Every run's ``gap.csv`` with a ``run`` column (the folder name)."""
    tables = [pd.read_csv(run / "gap.csv").assign(run=run.name) for run in runs]
    return pd.concat(tables, ignore_index=True)


def values(table: pd.DataFrame) -> list[str]:
    """The values of a gap row, % localized: the baseline's (the column not in `COLUMNS`), untrained,
    trained, ground truth."""
    baseline = [column for column in table.columns if column not in COLUMNS]
    if len(baseline) != 1:
        raise ValueError(
            f"gap.csv: expected one baseline column beside {list(COLUMNS)}, "
            f"found {baseline} (runs of one report.baseline)"
        )
    return [baseline[0], "untrained", "trained", "groundtruth_value"]


def with_means(table: pd.DataFrame) -> pd.DataFrame:
    """``table`` and, per metric, a row ``run == "mean"``: the means over runs and the gap closed of the means."""
    shown_values = values(table)
    baseline = shown_values[0]
    means = table.groupby("metric", sort=False)[shown_values].mean().reset_index().assign(run="mean")
    means["gap_closed_pct"] = (
        100 * (means["trained"] - means[baseline]) / (means["groundtruth_value"] - means[baseline])
    )
    means["groundtruth"] = table.groupby("metric", sort=False)["groundtruth"].first().values
    shown = pd.concat([table, means], ignore_index=True)[
        ["metric", "run", *shown_values, "groundtruth", "gap_closed_pct"]
    ]
    return shown.sort_values(["metric", "run"], key=lambda column: column.map(lambda value: (value == "mean", value)))


def markdown(table: pd.DataFrame) -> str:
    """One row per run and paradigm metric, then the mean over runs per metric with its gap closed."""
    return with_means(table).to_markdown(index=False, floatfmt=".1f")


def wide_markdown(table: pd.DataFrame) -> str:
    """One row per run (then the mean), one column per metric: ``densevlad / untrained / trained /
    ground truth (gap closed %)``."""
    shown = with_means(table)
    cells = shown.apply(
        lambda row: " / ".join(f"{row[value]:.1f}" for value in values(table)) + f" ({row['gap_closed_pct']:.0f} %)",
        axis=1,
    )
    wide = shown.assign(cell=cells).pivot(index="run", columns="metric", values="cell")
    wide = wide.loc[sorted(wide.index, key=lambda run: (run == "mean", run)), list(dict.fromkeys(shown["metric"]))]
    return wide.reset_index().to_markdown(index=False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--wide", action="store_true", help="one row per run, one cell per paradigm")
    arguments = parser.parse_args()
    table = load(arguments.runs)
    print(wide_markdown(table) if arguments.wide else markdown(table))


if __name__ == "__main__":
    main()
