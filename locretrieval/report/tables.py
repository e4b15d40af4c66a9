"""The tidy tables of finished runs, read and combined (one run, or a multirun's runs)."""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from locretrieval.errors import DataFileError
from locretrieval.metrics.localization import QUERY_ERROR_COLUMNS, QUERY_LOCALIZED_COLUMNS, RESULT_COLUMNS
from locretrieval.metrics.retrieval import QUERY_RETRIEVAL_COLUMNS, RETRIEVAL_COLUMNS
from locretrieval.metrics.revisited import REVISITED_COLUMNS
from locretrieval.metrics.subsets import SUBSET_COLUMNS
from locretrieval.report.run_files import RERUN, load_yaml, run_file
from locretrieval.scene.types import METRES

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TableSpec:
    """A run's table file, the columns it must hold and those that identify a row; ``derived``:
    columns that runs of earlier versions lack, copied from another (``{column: source}``);
    ``defaults``: columns they lack, with the value they meant (``{column: value}``; NaN: unknown,
    e.g. the intervals earlier versions did not compute)."""

    file: str
    columns: list[str]
    keys: list[str]
    derived: dict[str, str] = field(default_factory=dict)
    defaults: dict[str, object] = field(default_factory=dict)


def _spec(
    file: str,
    columns: list[str],
    values: Sequence[str],
    derived: dict[str, str] | None = None,
    defaults: dict[str, object] | None = None,
) -> TableSpec:
    return TableSpec(file, columns, [c for c in columns if c not in values], derived or {}, defaults or {})


UNKNOWN = float("nan")
#: The columns of the localization tables earlier versions did not write: positions were metres.
LOCALIZATION_DEFAULTS = {
    "localized": UNKNOWN,
    "localized_low_pct": UNKNOWN,
    "localized_high_pct": UNKNOWN,
    "position_unit": METRES,
}


#: Tables of a run directory; only ``results`` is required.
TABLES: dict[str, TableSpec] = {
    "results": _spec(
        "results.csv",
        RESULT_COLUMNS,
        ["localized_pct", "num_queries", *LOCALIZATION_DEFAULTS],
        {"k_effective": "k"},
        LOCALIZATION_DEFAULTS,
    ),
    "query_localized": _spec("query_localized.csv.gz", QUERY_LOCALIZED_COLUMNS, ["localized"]),
    "query_errors": _spec(
        "query_errors.csv.gz",
        QUERY_ERROR_COLUMNS,
        ["position_error_m", "rotation_error_deg", "failure", "position_unit"],
        defaults={"position_unit": METRES},
    ),
    "retrieval": _spec(
        "retrieval.csv",
        RETRIEVAL_COLUMNS,
        ["value", "num_queries", "value_low", "value_high"],
        defaults={"value_low": UNKNOWN, "value_high": UNKNOWN},
    ),
    "query_retrieval": _spec("query_retrieval.csv.gz", QUERY_RETRIEVAL_COLUMNS, ["value"]),
    "groundtruth_statistics": TableSpec(
        "groundtruth_statistics.csv", columns=["dataset", "groundtruth"], keys=["dataset", "groundtruth"]
    ),
    "subsets": TableSpec("subsets.csv", SUBSET_COLUMNS, ["dataset", "image"]),
    "revisited": _spec("revisited.csv", REVISITED_COLUMNS, ["value", "num_queries"]),
}

#: Columns read as text, verbatim (never as numbers or NaN): names and labels.
TEXT_COLUMNS = {
    "dataset", "subset", "ranking", "ranking_kind", "groundtruth", "paradigm", "method", "metric",
    "query", "image", "failure", "mask_source", "protocol", "position_unit",
}  # fmt: skip

#: Optional free-form summary of a run (``{"label": value}``), shown in the report.
SUMMARY_FILE = "summary.json"
#: The key of `SUMMARY_FILE` holding each SfM stage's seconds, work done and unit (`StageRecord`).
SFM_STAGES = "SfM stages"


@dataclass
class RunTables:
    """Every table of one or several runs, concatenated without duplicate rows."""

    run_dirs: list[Path]
    results: pd.DataFrame
    query_localized: pd.DataFrame
    query_errors: pd.DataFrame
    retrieval: pd.DataFrame
    query_retrieval: pd.DataFrame
    groundtruth_statistics: pd.DataFrame
    subsets: pd.DataFrame
    revisited: pd.DataFrame
    summaries: dict[str, dict] = field(default_factory=dict)


def find_run_dirs(paths: Sequence[str | Path]) -> list[Path]:
    """Run directories (holding ``results.csv``) among ``paths`` or below them (a multirun)."""
    found: list[Path] = []
    for path in map(Path, paths):
        if (path / TABLES["results"].file).is_file():
            found.append(path)
            continue
        below = sorted(p.parent for p in path.rglob(TABLES["results"].file)) if path.is_dir() else []
        if not below:
            raise FileNotFoundError(f"no {TABLES['results'].file} in {path} or below it: not a finished evaluation run")
        found += below
    return list(dict.fromkeys(found))


def read_table(path: Path, spec: TableSpec) -> pd.DataFrame:
    """One table file; a missing optional file or a header-only file gives an empty table, one
    without the spec's columns a `DataFileError`. Every column but `TEXT_COLUMNS` holds numbers (an
    empty field: none); anything else is a `DataFileError` naming the file, the line and the column
    (`numeric_columns`)."""
    if not path.is_file():
        return pd.DataFrame(columns=spec.columns)
    try:
        header = list(pd.read_csv(path, nrows=0).columns)
    except pd.errors.EmptyDataError:
        return pd.DataFrame(columns=spec.columns)
    missing = [c for c in spec.columns if c not in header and c not in spec.derived and c not in spec.defaults]
    if missing:
        raise DataFileError(path, f"missing columns {missing} (found {header})")
    text = [c for c in header if c in TEXT_COLUMNS]
    table = pd.read_csv(
        path,
        dtype={c: str for c in text},
        keep_default_na=False,
        na_values={c: [""] for c in header if c not in text},
    )
    unparsed = [  # columns where pandas found text
        c for c in table.columns if c not in text and not pd.api.types.is_numeric_dtype(table[c])
    ]
    table = numeric_columns(table, unparsed, path)
    table = table.assign(**{column: value for column, value in spec.defaults.items() if column not in header})
    return table.assign(**{column: table[source] for column, source in spec.derived.items() if column not in header})


def numeric_columns(table: pd.DataFrame, columns: Sequence[str], path: Path) -> pd.DataFrame:
    """``table`` with ``columns`` (text as read) as numbers: an empty field is none (NaN, as pandas
    writes it); a field that is not a number, or the text ``nan``, is a `DataFileError` naming the
    file, its line and the column."""
    converted = {}
    for column in columns:
        text = table[column].astype(str).str.strip().where(table[column].notna(), "")
        numbers = pd.to_numeric(text.where(text != ""), errors="coerce")
        wrong = (text != "") & (numbers.isna())
        if wrong.any():
            row = int(wrong.to_numpy().nonzero()[0][0])
            raise DataFileError(
                path,
                f"line {row + 2}, column {column!r}: {text.iloc[row][:80]!r} is not a number "
                "(a missing value is an empty field)",
                RERUN,
            )
        converted[column] = numbers
    return table.assign(**converted)


def conflicting_rows(frames: Sequence[tuple[Path, pd.DataFrame]], spec: TableSpec) -> pd.DataFrame:
    """The rows of several runs' tables (column ``_run`` added) whose keys repeat with different values."""
    frames = [(run, frame) for run, frame in frames if len(frame)]
    if not frames:
        return pd.DataFrame(columns=[*spec.columns, "_run"])
    table = pd.concat([frame.assign(_run=str(run)) for run, frame in frames], ignore_index=True)
    values = [c for c in table.columns if c not in spec.keys and c != "_run"]
    distinct = table.drop_duplicates(subset=spec.keys + values)
    return distinct[distinct.duplicated(subset=spec.keys, keep=False)]


def combine(frames: Sequence[tuple[Path, pd.DataFrame]], spec: TableSpec) -> pd.DataFrame:
    """Concatenate one table of several runs, dropping rows repeated across runs.

    Rows with the same keys (e.g. a ground-truth ranking evaluated in every run of a multirun
    over models) are kept once. Rankings whose rows differ are renamed per run beforehand
    (`label_variants`); the per-image and per-definition tables left (``subsets.csv``,
    ``groundtruth_statistics.csv``) keep the first run's row, with a warning.
    """
    frames = [(run, frame) for run, frame in frames if len(frame)]
    if not frames:
        return pd.DataFrame(columns=spec.columns)
    conflicting = conflicting_rows(frames, spec)
    if len(conflicting):
        log.warning(
            "%d rows of %s differ between runs for the same keys, e.g. %s in %s; keeping the first run's values",
            len(conflicting), spec.file, conflicting.iloc[0][spec.keys].to_dict(), sorted(set(conflicting["_run"])),
        )  # fmt: skip
    table = pd.concat([frame for _, frame in frames], ignore_index=True)
    return table.drop_duplicates(subset=spec.keys).reset_index(drop=True)


def run_variants(run_dirs: Sequence[Path]) -> dict[Path, str]:
    """A label per run: the Hydra command-line overrides (``.hydra/overrides.yaml``) that are not
    shared by every run, e.g. ``paradigms.approximation.weights.csi.alpha=4``; the directory name otherwise."""
    overrides = {}
    for run in run_dirs:
        path = run_file(run, Path(".hydra", "overrides.yaml"))
        listed = load_yaml(path) if path.is_file() else []  # as written: no interpolation resolved
        overrides[run] = [str(item) for item in listed] if isinstance(listed, list) else []
    shared = set.intersection(*(set(items) for items in overrides.values())) if overrides else set()
    labels = {run: ", ".join(item for item in items if item not in shared) for run, items in overrides.items()}
    return {run: label or run.name for run, label in labels.items()}


def label_variants(raw: dict[Path, dict[str, pd.DataFrame]]) -> None:
    """Rename, in place, each ranking whose rows differ between runs (a model, a ground truth or
    a baseline evaluated under several settings, e.g. a sweep over the CSI exponent) to
    ``name [variant]``, so that no run's rows replace another's."""
    clashing: set[str] = set()
    for name, spec in TABLES.items():
        if "ranking" in spec.keys:
            clashing |= set(conflicting_rows([(run, tables[name]) for run, tables in raw.items()], spec)["ranking"])
    if not clashing:
        return
    variants = run_variants(list(raw))
    if len(set(variants.values())) < len(variants):
        raise ValueError(
            f"rankings {sorted(clashing)} differ between runs {sorted(map(str, raw))} that no Hydra override "
            "or directory name tells apart (e.g. two different descriptors share a name); report them separately"
        )
    log.info("rankings %s differ between runs: labelled by run (%s)", sorted(clashing), "; ".join(variants.values()))
    for run, tables in raw.items():
        for table in tables.values():
            if "ranking" in table and len(table):
                renamed = table["ranking"].isin(clashing)
                table.loc[renamed, "ranking"] = table.loc[renamed, "ranking"] + f" [{variants[run]}]"


def load_runs(paths: Sequence[str | Path]) -> RunTables:
    """Read and combine the tables of the runs at or below ``paths``."""
    run_dirs = find_run_dirs(paths)
    raw = {run: {name: read_table(run_file(run, spec.file), spec) for name, spec in TABLES.items()} for run in run_dirs}
    label_variants(raw)
    tables = {name: combine([(run, raw[run][name]) for run in run_dirs], spec) for name, spec in TABLES.items()}
    summaries = {}
    for run in run_dirs:
        if run_file(run, SUMMARY_FILE).is_file():
            try:
                summary = json.loads((run / SUMMARY_FILE).read_text())
            except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as error:
                raise DataFileError(run / SUMMARY_FILE, f"not valid JSON ({error})", RERUN) from None
            if not isinstance(summary, dict):
                raise DataFileError(run / SUMMARY_FILE, "not a JSON object of labels and values", RERUN)
            summaries[str(run)] = summary
    log.info("report over %d run(s): %s", len(run_dirs), ", ".join(map(str, run_dirs)))
    return RunTables(run_dirs=run_dirs, summaries=summaries, **tables)
