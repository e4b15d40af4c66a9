"""The reference tools' published results, shipped as CSV, and the run's numbers beside them.

kapture-localization publishes, per dataset, the % of queries localized per global feature,
local feature, paradigm, k, query condition and accuracy threshold, with the median position
(metres) and rotation (degrees) errors for some (``published/<dataset>.csv``, converted from
its ``doc/benchmark_results_<dataset>.adoc`` by ``scripts/convert_published_results.py``; the
source commit is in ``published/SOURCES.md``). Their medians count a query without an estimate
as an infinite error (``inf`` where fewer than half are localized).

A run's row matches a published row when the dataset (``data.name``), the global feature
(`GLOBAL_FEATURES`: our model name -> theirs; a published name matches itself), the local
feature (`LOCAL_FEATURES`, from the run's ``config.yaml``), the paradigm and method, k, the
query subset (published condition ``all``, ``day``, ``night``, ``validation``, ``test``) and
the threshold (metres, degrees) are all equal.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from locretrieval.report.markdown import ReportWriter, md_text
from locretrieval.report.plots import threshold_label
from locretrieval.report.run_files import load_yaml, mapping_at, run_file
from locretrieval.report.tables import TABLES, read_table

#: The shipped CSVs, one per dataset.
PUBLISHED_DIR = Path(__file__).parent / "published"

#: Columns of a published CSV: one row per dataset x local feature x global feature x paradigm x
#: method x k x condition x threshold; medians (per condition) repeat on each threshold's row.
PUBLISHED_COLUMNS = [
    "dataset", "local_feature", "global_feature", "paradigm", "method", "k", "condition",
    "position_threshold_m", "rotation_threshold_deg", "localized_pct",
    "median_position_error_m", "median_rotation_error_deg",
]  # fmt: skip

#: Our model names (configs/model/*.yaml ``name``) -> the published global feature they reproduce.
GLOBAL_FEATURES = {
    "apgem": "AP-GeM-LM18",  # Resnet101-AP-GeM-LM18.pt
    "delg": "r101delg_gldv2clean",  # r101delg_gldv2clean_20200914 (their "DELG" is another model)
    "densevlad": "densevlad_multi",
    "netvlad": "netvlad_vd16pitts",  # Pitts30k VGG16 (their openibl_vgg16_netvlad is another)
}

#: Kapture local-feature folder names (``sfm.features.name``) -> the published local feature.
#: Both published sets have 20,000 keypoints per image: a run keeping fewer (``max_keypoints``) matches neither.
LOCAL_FEATURES = {
    "r2d2_WASF-N8_20k": "r2d2_WASF_N8_big 20k",  # the kapture downloader's name of the paper's R2D2 features
    "r2d2_WASF_N8_big": "r2d2_WASF_N8_big 20k",
}
PUBLISHED_KEYPOINTS = 20000

#: Published table sections -> our (paradigm, method).
PARADIGMS = {"global_sfm": ("global_sfm", "pnp"), "local_sfm": ("local_sfm", "pnp"), "EWB": ("approximation", "ewb")}

#: Columns a run's row and a published row must share to match.
MATCH_KEYS = [
    "dataset", "local_feature", "global_feature", "paradigm", "method", "k", "condition",
    "position_threshold_m", "rotation_threshold_deg",
]  # fmt: skip

#: Published medians as the comparison table names them.
MEDIANS = {"median_position_error_m": "published median m", "median_rotation_error_deg": "published median deg"}

_THRESHOLD = re.compile(r"\(\s*([\d.]+)\s*m?\s*[_,]\s*([\d.]+)\s*(?:deg)?\s*\)")
_SPAN = re.compile(r"(.*?)\s*(\d+)\+\s*")


def parse_adoc(text: str, dataset: str, source: str) -> pd.DataFrame:
    """The tables of a ``benchmark_results_<dataset>.adoc`` as rows of `PUBLISHED_COLUMNS`
    (``source`` names the file in errors)."""
    rows: list[dict] = []
    local_feature = paradigm = None
    lines = text.splitlines()
    number = 0
    while number < len(lines):
        line = lines[number].strip()
        if line.startswith("== ") and line.endswith(" Results"):
            local_feature = line[3 : -len(" Results")].strip()
        elif line.startswith("=== "):
            paradigm = line[4:].strip()
        elif line.startswith("[%header"):
            if lines[number + 1].strip() != "|===":
                raise ValueError(f"{source}, line {number + 2}: '|===' expected after {line!r}")
            end = next((n for n in range(number + 2, len(lines)) if lines[n].strip() == "|==="), None)
            if end is None:
                raise ValueError(f"{source}, line {number + 2}: table never closed by '|==='")
            table = [(n + 1, lines[n]) for n in range(number + 2, end) if lines[n].strip()]
            where = f"{source}, table at line {number + 1}"
            if local_feature is None or paradigm not in PARADIGMS:
                raise ValueError(
                    f"{where}: outside a '== <local feature> Results' / '=== <paradigm>' section ({paradigm!r})"
                )
            separator = ";" if "format=csv" in line else "|"
            for record in _table_rows(table, separator, where):
                rows.append({"dataset": dataset, "local_feature": local_feature, **_paradigm(paradigm), **record})
            number = end
        number += 1
    if not rows:
        raise ValueError(f"{source}: no benchmark table found")
    return pd.DataFrame(rows, columns=PUBLISHED_COLUMNS)


def _paradigm(section: str) -> dict[str, str]:
    paradigm, method = PARADIGMS[section]
    return {"paradigm": paradigm, "method": method}


def _cells(line: str, separator: str) -> list[str]:
    cells = line.split(separator)
    return [cell.strip() for cell in (cells[1:] if separator == "|" else cells)]


def _table_rows(table: list[tuple[int, str]], separator: str, where: str) -> list[dict]:
    """The records of one table: its header (conditions, then labels; a CSV table has only
    labels and covers all queries), then a record per feature x k x condition x threshold."""
    if separator == "|":
        conditions, labels = _spanned(table[0][1]), _cells(table[1][1], "|")
        body = table[2:]
    else:
        labels, body = _cells(table[0][1], ";"), table[1:]
        conditions = ["", ""] + ["all"] * (len(labels) - 2)
    if len(conditions) != len(labels):
        raise ValueError(f"{where}: {len(conditions)} columns under conditions but {len(labels)} labels")
    columns = [(condition, _label(label, where)) for condition, label in zip(conditions[2:], labels[2:])]
    records = []
    for number, line in body:
        cells = _cells(line, separator)
        if not any(cells):
            continue  # the blank rows between blocks of k
        if len(cells) != len(labels):
            raise ValueError(f"{where}, line {number}: {len(cells)} cells, the header has {len(labels)}")
        records += _records(cells[0], int(cells[1]), columns, cells[2:], f"{where}, line {number}")
    return records


def _spanned(line: str) -> list[str]:
    """The condition of every column of a header row such as ``|feature type|topk 3+|day 3+|night``
    (``N+|`` makes the next cell span N columns), lower-cased."""
    conditions, span = [], 1
    for cell in _cells(line, "|"):
        match = _SPAN.fullmatch(cell)
        conditions += [(match.group(1) if match else cell).strip().lower()] * span
        span = int(match.group(2)) if match else 1
    return conditions


def _label(label: str, where: str) -> tuple[float, float] | str:
    """A column label: ``(metres, degrees)`` of a threshold, or which median it holds."""
    if label.startswith("median distance"):
        return "median_position_error_m"
    if label.startswith("median angle"):
        return "median_rotation_error_deg"
    match = _THRESHOLD.fullmatch(label)
    if match is None:
        raise ValueError(f"{where}: unknown column label {label!r}")
    return float(match.group(1)), float(match.group(2))


def _records(feature: str, k: int, columns: list, values: list[str], where: str) -> list[dict]:
    """One record per condition x threshold of a table row, the condition's medians attached."""
    parsed = [_number(value, where) for value in values]
    medians: dict[str, dict[str, float]] = {}
    for (condition, label), value in zip(columns, parsed):
        if isinstance(label, str):
            medians.setdefault(condition, {})[label] = value
    return [
        {
            "global_feature": feature,
            "k": k,
            "condition": condition,
            "position_threshold_m": label[0],
            "rotation_threshold_deg": label[1],
            "localized_pct": value,
            **medians.get(condition, {}),
        }  # fmt: skip
        for (condition, label), value in zip(columns, parsed)
        if not isinstance(label, str)
    ]


def _number(value: str, where: str) -> float:
    try:
        return float(value.rstrip("%"))
    except ValueError:
        raise ValueError(f"{where}: {value!r} is not a number") from None


@functools.cache
def load_published(folder: Path) -> pd.DataFrame:
    """Every shipped ``<dataset>.csv`` of ``folder``, concatenated (`PUBLISHED_COLUMNS`)."""
    frames = []
    for path in sorted(Path(folder).glob("*.csv")):
        table = pd.read_csv(path, dtype={"global_feature": str, "local_feature": str, "condition": str})
        missing = [column for column in PUBLISHED_COLUMNS if column not in table]
        if missing:
            raise ValueError(f"{path}: missing columns {missing} (found {list(table.columns)})")
        frames.append(table[PUBLISHED_COLUMNS])
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=PUBLISHED_COLUMNS)


def local_feature(run_dir: Path) -> tuple[str, str | None]:
    """The run's local features as configured (``config.yaml``'s ``sfm.features``) and their
    published name (`LOCAL_FEATURES`; ``None`` when nothing published used them)."""
    path = run_file(run_dir, "config.yaml")
    if not path.is_file():
        return "unknown (no config.yaml)", None
    features = mapping_at(load_yaml(path), "sfm", "features")  # as written: no interpolation resolved
    target = str(features.get("_target_", ""))
    # the kind: SiftFeatures -> sift; runs before sfm.features had a _target_ wrote `type` and `kapture.name`
    kind = (
        target.rsplit(".", 1)[-1].removesuffix("Features").lower() if target else str(features.get("type", "unknown"))
    )
    if kind != "kapture":
        return kind, None
    name, kept = str(features.get("name") or mapping_at(features, "kapture").get("name")), features.get("max_keypoints")
    described = f"kapture {name}" + (f" (best {kept})" if kept is not None else "")
    full = kept is None or (isinstance(kept, (int, float)) and kept >= PUBLISHED_KEYPOINTS)
    return described, LOCAL_FEATURES.get(name, name) if full else None


def published_name(ranking: str) -> str:
    """The published global feature a ranking's name stands for (itself when not in `GLOBAL_FEATURES`)."""
    return GLOBAL_FEATURES.get(ranking, ranking)


def compare(results: pd.DataFrame, published: pd.DataFrame, local: str | None) -> pd.DataFrame:
    """The rows of ``results`` (a run's ``results.csv``, local features published as ``local``)
    that a published row matches: our % localized, theirs and ``difference`` (ours - theirs,
    percentage points), with the published medians."""
    if local is None or results.empty or published.empty:
        return pd.DataFrame()
    ours = results.assign(
        global_feature=results["ranking"].map(published_name), local_feature=local, condition=results["subset"]
    )
    merged = _rounded(ours).merge(_rounded(published), on=MATCH_KEYS, suffixes=("", "_published"))
    return merged.assign(difference=merged["localized_pct"] - merged["localized_pct_published"])


def _rounded(table: pd.DataFrame) -> pd.DataFrame:
    """Thresholds rounded to micrometres and microdegrees, so that 0.25 read twice matches."""
    return table.assign(
        k=table["k"].astype(int),
        position_threshold_m=table["position_threshold_m"].astype(float).round(6),
        rotation_threshold_deg=table["rotation_threshold_deg"].astype(float).round(6),
    )


def looked_for(results: pd.DataFrame, described: str, local: str | None) -> str:
    """What a run offered to match, in words (the report's line when nothing matches)."""
    rankings = sorted(set(results["ranking"]))
    features = ", ".join(r if published_name(r) == r else f"{r} (as {published_name(r)})" for r in rankings) or "none"
    paradigms = ", ".join(sorted({f"{p}/{m}" for p, m in zip(results["paradigm"], results["method"])})) or "none"
    return (
        f"dataset {', '.join(sorted(set(results['dataset']))) or 'none'}; global features {features}; local features "
        f"{described}{f' (as {local})' if local and local != described else ''}; paradigms {paradigms}"
    )


def published_section(writer: ReportWriter, run_dirs: Sequence[Path], folder: Path | None = None) -> None:
    """The report's section: each run's descriptor rows beside the published ones (the CSVs of
    ``folder``, default `PUBLISHED_DIR`), or one line saying what was looked for when nothing matches."""
    writer.heading("Published results (kapture-localization)")
    published = load_published(Path(folder or PUBLISHED_DIR))
    comparisons, searched = [], []
    for run in run_dirs:
        results = read_table(run_file(run, TABLES["results"].file), TABLES["results"])
        results = results[results["ranking_kind"] == "descriptor"]
        described, local = local_feature(run)
        comparisons.append(compare(results, published, local))
        searched.append(looked_for(results, described, local))
    matched = pd.concat(comparisons, ignore_index=True) if comparisons else pd.DataFrame()
    datasets = ", ".join(sorted(set(published["dataset"])))
    if matched.empty:
        looked = md_text(" | ".join(searched))
        writer.text(f"No published result matches this run: looked for {looked} (published: {md_text(datasets)}).")
        return
    caption = (
        "% of queries localized by this run and as published by kapture-localization (source and commit: "
        "locretrieval/report/published/SOURCES.md), difference = ours - published in percentage points. "
        "Published medians count a "
        "query without an estimate as an infinite error (inf: "
        "fewer than half localized); this run's are under Median errors."
    )
    writer.table(comparison_table(matched), "published_comparison", caption, ".1f")


def comparison_table(matched: pd.DataFrame) -> pd.DataFrame:
    """`compare`'s rows for the report: a row per dataset x condition x ranking x paradigm x
    method x k x threshold, columns ours, published, difference."""
    pairs = zip(matched["position_threshold_m"], matched["rotation_threshold_deg"])
    table = matched.assign(
        threshold=[threshold_label(x, y) for x, y in pairs],
        ranking=[r if r == g else f"{r} ({g})" for r, g in zip(matched["ranking"], matched["global_feature"])],
    )
    keys = ["dataset", "condition", "local_feature", "ranking", "paradigm", "method", "k", "threshold"]
    table = table.drop_duplicates(keys).sort_values(keys)
    values = table.set_index(keys)[["localized_pct", "localized_pct_published", "difference", *MEDIANS]]
    return values.rename(columns={"localized_pct": "ours %", "localized_pct_published": "published %", **MEDIANS})
