"""Markdown and LaTeX tables of the report, and the ``report.md`` writer.

Every string that comes from data or a configuration (names of images, folders, tags, models,
rankings, ground truths, runs; error texts) is escaped where it is written: `md_text` (literal
Markdown text, table cells included), `md_code` (a code span), `md_link` (a relative link),
`latex_text` (LaTeX); tables escape their cells and labels (`write_table`, `markdown_table`).
"""

from __future__ import annotations

import re
import urllib.parse
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future
from functools import partial
from pathlib import Path

import pandas as pd

from locretrieval.cache import safe_name
from locretrieval.report.plots import threshold_label

#: Characters Markdown (GitHub's and Python-Markdown's, tables included) or HTML could read as
#: markup: written as numeric character references, which both show as the character. Where a
#: plain character is safe it stays one: a ``&`` that starts no character reference, a ``]`` that
#: closes no link, image or link definition (none before ``(``, ``[`` or ``:``; a ``[`` alone
#: opens nothing), an ``_`` inside a word.
_MARKUP = re.compile(r"[\\`*<>|$~]|&(?=#?\w+;)|\](?=[(\[:])|(?<![A-Za-z0-9])_|_(?![A-Za-z0-9])")
#: Brackets in a link's label (`md_link`), where every one could end or nest the label.
_BRACKETS = re.compile(r"[\[\]]")
_LINE_BREAK = re.compile(r"[\r\n\t\v\f\u2028\u2029]+")
#: LaTeX's special characters and what writes them literally.
_LATEX = {
    "\\": r"\textbackslash{}", "{": r"\{", "}": r"\}", "$": r"\$", "&": r"\&", "#": r"\#", "%": r"\%",
    "_": r"\_", "^": r"\textasciicircum{}", "~": r"\textasciitilde{}",
}  # fmt: skip


def md_text(value: object) -> str:
    """``value`` as literal Markdown text (a table cell too): markup characters become character
    references, line breaks spaces; names without them (``AP-GeM-LM18``, ``synthetic_mall``) are unchanged."""
    return _MARKUP.sub(lambda match: f"&#{ord(match.group())};", _LINE_BREAK.sub(" ", str(value)))


def md_code(value: object) -> str:
    """``value`` as a Markdown code span (not in a table: use `md_text`): fenced by one backtick more
    than the longest run of backticks it holds, so that no backtick in it closes the span."""
    text = _LINE_BREAK.sub(" ", str(value))
    fence = "`" * (max((len(run) for run in re.findall("`+", text)), default=0) + 1)
    padding = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{padding}{text}{padding}{fence}"


def md_link(label: object, target: str) -> str:
    """A Markdown link to the relative path ``target`` (percent-encoded) labelled ``label`` (`md_text`,
    its brackets escaped too)."""
    text = _BRACKETS.sub(lambda match: f"&#{ord(match.group())};", md_text(label))
    return f"[{text}]({urllib.parse.quote(target)})"


def md_image(label: object, target: str) -> str:
    """A Markdown image of the relative path ``target`` (percent-encoded), its alternative text
    ``label`` (`md_text`)."""
    return f"!{md_link(label, target)}"


def latex_text(value: object) -> str:
    """``value`` as literal LaTeX text (captions; `write_table` escapes cells and labels)."""
    return "".join(_LATEX.get(character, character) for character in _LINE_BREAK.sub(" ", str(value)))


def markdown_table(frame: pd.DataFrame, **options) -> str:
    """``frame`` (index and columns flat) as a Markdown table, its string cells and labels `md_text`."""
    labels = {"index": lambda label: md_text(label) if isinstance(label, str) else label, "columns": md_text}
    escaped = frame.rename(**labels).map(lambda value: md_text(value) if isinstance(value, str) else value)
    return escaped.to_markdown(**options)


class ReportWriter:
    """Accumulates the markdown of a report whose figures and tables live below ``directory``."""

    def __init__(self, directory: Path, title: str) -> None:
        self.directory = directory
        self.lines: list[str | Callable[[], list[str]]] = [f"# {title}", ""]

    def heading(self, text: str, level: int = 2) -> None:
        """A heading; ``text`` is Markdown (data and config strings in it escaped by the caller)."""
        self.lines += [f"{'#' * level} {text}", ""]

    def text(self, *paragraphs: str) -> None:
        for paragraph in paragraphs:
            self.lines += [paragraph, ""]

    def bullets(self, items: Mapping[str, object] | Sequence[tuple[str, object]]) -> None:
        """A list of ``**key**: value`` (a key may repeat when given as pairs); both are Markdown
        (strings from data escaped by the caller)."""
        pairs = items.items() if isinstance(items, Mapping) else items
        self.lines += [f"- **{key}**: {value}" for key, value in pairs] + [""]

    def image(self, label: object, target: str) -> None:
        """An image (`md_image`) of the relative path ``target``."""
        self.lines += [md_image(label, target), ""]

    def figures(self, paths: Sequence[Path] | Future) -> None:
        """Links to the figures ``paths`` (or the future of a figure worker's, awaited by `write`)."""
        self.lines.append(partial(self._figure_links, paths))

    def _figure_links(self, paths: Sequence[Path] | Future) -> list[str]:
        paths = paths.result() if isinstance(paths, Future) else paths
        return [
            line for path in paths for line in (f"![{path.stem}]({path.relative_to(self.directory).as_posix()})", "")
        ]

    def table(self, frame: pd.DataFrame, stem: str, caption: str, floatfmt: str = ".2f") -> None:
        """Embed ``frame`` and write it as ``tables/<stem>.md`` and ``tables/<stem>.tex``."""
        stem = safe_name(stem)
        markdown = write_table(frame, self.directory / "tables", stem, caption, floatfmt)
        self.lines += [f"{md_text(caption)} ([LaTeX](tables/{stem}.tex))", "", markdown, ""]

    def write(self, path: Path) -> Path:
        """Write ``report.md`` once every figure it links is drawn."""
        lines = [part for line in self.lines for part in (line() if callable(line) else [line])]
        path.write_text("\n".join(lines).rstrip() + "\n")
        return path


def write_table(frame: pd.DataFrame, directory: Path, stem: str, caption: str, floatfmt: str = ".2f") -> str:
    """Write ``frame`` as ``<stem>.md`` and ``<stem>.tex`` (booktabs); returns the markdown.

    Missing values (e.g. undefined correlations) print as ``–`` (``--`` in LaTeX). Strings are
    written literally: `md_text` in Markdown, escaped in LaTeX (``caption`` is plain text).
    """
    directory.mkdir(parents=True, exist_ok=True)
    flat = frame.reset_index()
    names = flat.columns.names
    flat.columns = [
        " ".join(_label(n, v) for n, v in zip(names, c)) if isinstance(c, tuple) else str(c) for c in flat.columns
    ]
    markdown = markdown_table(
        flat.astype(object).where(flat.notna(), None), index=False, floatfmt=floatfmt, missingval="–"
    )
    (directory / f"{stem}.md").write_text(markdown + "\n")
    latex = frame.to_latex(
        index=True,
        float_format=lambda value: format(value, floatfmt),
        na_rep="--",
        escape=True,  # cells, index and column labels
        caption=latex_text(caption),
        label=f"tab:{stem}",
    )
    (directory / f"{stem}.tex").write_text(latex)
    return markdown


def _label(level: str | None, value: object) -> str:
    return f"k={value}" if level == "k" and value != "" else str(value)


def interval_text(value: float, low: float, high: float, digits: int = 1) -> str:
    """``79.7 (68.3–87.7)``: a figure and its interval; the figure alone where the interval is not
    known (a run of an earlier version), ``–`` where there is no figure (the captions say when)."""
    if pd.isna(value):
        return "–"
    if pd.isna(low) or pd.isna(high):
        return f"{value:.{digits}f}"
    return f"{value:.{digits}f} ({low:.{digits}f}–{high:.{digits}f})"


def difference_text(difference: float, low: float, high: float, verdict: str) -> str:
    """``+12.5 (+3.1 to +21.9) better``: a paired difference in points, its interval and verdict."""
    return f"{difference:+.1f} ({low:+.1f} to {high:+.1f}) {verdict}"


def localized_text(rows: pd.DataFrame, with_k: bool = False) -> list[str]:
    """Each localization row's % localized with its interval (`interval_text`), and its k."""
    texts = [
        interval_text(row.localized_pct, row.localized_low_pct, row.localized_high_pct) for row in rows.itertuples()
    ]
    return [f"{text}, k={k}" for text, k in zip(texts, rows["k"])] if with_k else texts


def pivot_localization(table: pd.DataFrame, paradigm: str, method: str) -> pd.DataFrame:
    """``(ranking, k) x threshold`` table of % localised with its interval for one paradigm/method,
    all queries: a row per ranking and k, a column per threshold, tightest first."""
    rows = table[(table["paradigm"] == paradigm) & (table["method"] == method) & (table["subset"] == "all")]
    rows, thresholds = _with_thresholds(rows)
    rows = rows.assign(text=localized_text(rows))
    return rows.pivot(index=["ranking", "k"], columns="threshold", values="text")[thresholds]


def best_rows(table: pd.DataFrame, keys: Sequence[str]) -> pd.DataFrame:
    """The row of each group of ``keys`` where the most queries were localized, the smallest k among equals."""
    ordered = table.sort_values(["localized_pct", "k"], ascending=[False, True], kind="stable")
    return ordered.drop_duplicates(list(keys))


def best_localization(table: pd.DataFrame) -> pd.DataFrame:
    """Best % localised over k with its interval and k, all queries:
    ``(dataset, paradigm, method, ranking) x threshold``."""
    rows, thresholds = _with_thresholds(table[table["subset"] == "all"])
    keys = ["dataset", "paradigm", "method", "ranking", "threshold"]
    best = best_rows(rows, keys)
    best = best.assign(text=localized_text(best, with_k=True))
    return best.set_index(keys)["text"].unstack("threshold")[thresholds]


def difference_table(best_k: pd.DataFrame) -> pd.DataFrame:
    """The headline's paired differences (`best_k_comparisons`): a row per dataset, paradigm, method
    and pair of rankings (those with a descriptor, and each ground truth against each baseline), a
    column per threshold: ``+12.5 (+3.1 to +21.9) better`` (points, ranking minus other, each at its best k)."""
    pairs = best_k[
        (best_k["ranking_kind"] == "descriptor")
        | (best_k["other_kind"] == "descriptor")
        | ((best_k["ranking_kind"] == "groundtruth") & (best_k["other_kind"] == "baseline"))
    ]
    if pairs.empty:
        return pd.DataFrame()
    pairs, thresholds = _with_thresholds(pairs)
    text = [
        difference_text(row.difference_pts, row.difference_low_pts, row.difference_high_pts, row.verdict)
        for row in pairs.itertuples()
    ]
    pairs = pairs.assign(text=text, pair=pairs["ranking"] + " vs " + pairs["other"])
    keys = ["dataset", "paradigm", "method", "pair", "threshold"]
    return pairs.set_index(keys)["text"].unstack("threshold")[thresholds]


def _with_thresholds(rows: pd.DataFrame) -> tuple[pd.DataFrame, list[str]]:
    """``rows`` with a ``threshold`` label column (in the rows' `position_unit`), and the labels in
    order, tightest first."""
    units = rows["position_unit"] if "position_unit" in rows else pd.Series("m", index=rows.index)
    triples = list(zip(rows["position_threshold_m"], rows["rotation_threshold_deg"], units))
    labels = [threshold_label(x, y, unit) for x, y, unit in sorted(set(triples))]
    return rows.assign(threshold=[threshold_label(x, y, unit) for x, y, unit in triples]), labels


def failure_summary(query_errors: pd.DataFrame) -> pd.DataFrame:
    """How many (query, k) estimates failed, per ranking x paradigm x method x reason."""
    failed = query_errors[query_errors["failure"].fillna("") != ""]
    return (
        failed.groupby(["ranking", "paradigm", "method", "failure"]).size().rename("count").reset_index()
        if len(failed)
        else pd.DataFrame(columns=["ranking", "paradigm", "method", "failure", "count"])
    )


def correlation_matrix(correlations: pd.DataFrame, across: str) -> pd.DataFrame:
    """Coefficients as ``(dataset, paradigm, method, threshold) x across`` (``ranking``
    for Pearson, Tables 3 and 6; ``k`` for Spearman, Tables 4 and 5), two decimals; an undefined
    one says why (``undefined: constant localization metric``)."""
    rows, _ = _with_thresholds(correlations)
    text = [
        f"undefined: {reason}" if pd.isna(value) else f"{value:.2f}"
        for value, reason in zip(rows["coefficient"], rows["undefined_reason"])
    ]
    return (
        rows.assign(text=text).set_index(["dataset", "paradigm", "method", "threshold", across])["text"].unstack(across)
    )


def undefined_summary(correlations: pd.DataFrame) -> pd.DataFrame:
    """How many coefficients are undefined, per reason."""
    undefined = correlations[correlations["undefined_reason"] != ""]
    return undefined.groupby("undefined_reason").size().rename("count").reset_index()


def retrieval_summary(retrieval: pd.DataFrame, ks: Sequence[int] = (1, 5, 10, 20, 50)) -> pd.DataFrame:
    """P@k, R@k and mAP@k in % with their intervals for a few k: ``(dataset, ground truth, ranking) x (metric, k)``."""
    rows = retrieval[(retrieval["subset"] == "all") & retrieval["k"].isin(list(ks))]
    low = rows["value_low"] if "value_low" in rows else pd.Series(float("nan"), index=rows.index)
    high = rows["value_high"] if "value_high" in rows else pd.Series(float("nan"), index=rows.index)
    text = [interval_text(100 * v, 100 * lo, 100 * hi) for v, lo, hi in zip(rows["value"], low, high)]
    keys = ["dataset", "groundtruth", "ranking", "metric", "k"]
    return rows.assign(text=text).set_index(keys)["text"].unstack(["metric", "k"]).sort_index(axis=1)


def median_error_summary(medians: pd.DataFrame) -> pd.DataFrame:
    """The median errors with their intervals and the % of queries with an estimate, one row per
    dataset, paradigm, method, ranking and k (`median_errors`)."""
    unit = medians["position_unit"].iloc[0] if "position_unit" in medians and len(medians) else "m"
    texts = {
        f"median position error ({unit})": ("median_position_error_m", "median_position_error_low_m", 2),
        "median rotation error (deg)": ("median_rotation_error_deg", "median_rotation_error_low_deg", 2),
        "% with an estimate": ("estimated_pct", "estimated_low_pct", 1),
    }
    columns = {}
    for title, (value, low, digits) in texts.items():
        high = low.replace("_low", "_high")
        missing = pd.Series(float("nan"), index=medians.index)
        columns[title] = [
            interval_text(v, lo, hi, digits)
            for v, lo, hi in zip(medians[value], medians.get(low, missing), medians.get(high, missing))
        ]
    keys = ["dataset", "paradigm", "method", "ranking", "k"]
    return pd.DataFrame(columns, index=pd.MultiIndex.from_frame(medians[keys]))


def revisited_summary(revisited: pd.DataFrame) -> pd.DataFrame:
    """mAP in % per ranking x (dataset, protocol), the paper's Table 2."""
    rows = revisited[revisited["metric"] == "map"]
    return rows.pivot_table(index="ranking", columns=["dataset", "protocol"], values="value").mul(100)


def subset_sizes(results: pd.DataFrame, retrieval: pd.DataFrame) -> pd.DataFrame:
    """Evaluated queries per dataset x subset."""
    columns = ["dataset", "subset", "num_queries"]
    sizes = pd.concat([results[columns], retrieval.loc[retrieval["metric"] != "map", columns]])
    return sizes.groupby(["dataset", "subset"])["num_queries"].max().unstack("subset")


def best_by_subset(results: pd.DataFrame) -> pd.DataFrame:
    """Best % localised over k with its interval at the loosest threshold, one column per subset
    (``paradigm, method, ranking`` rows)."""
    loosest = results[results["position_threshold_m"] == results["position_threshold_m"].max()]
    keys = ["paradigm", "method", "ranking", "subset"]
    best = best_rows(loosest, keys)
    return best.assign(text=localized_text(best)).set_index(keys)["text"].unstack("subset")


def separation_lines(separation: pd.DataFrame, units: Mapping[str, str]) -> list[str]:
    """A sentence per paradigm and threshold where no ground truth is distinguishable from the baseline
    (`locretrieval.metrics.comparison.separation`; ``units``: each dataset's position unit): that
    paradigm cannot rank descriptors there."""
    lines = []
    for row in separation[~separation["separates"].astype(bool)].itertuples():
        threshold = threshold_label(row.position_threshold_m, row.rotation_threshold_deg, units.get(row.dataset, "m"))
        lines.append(
            f"**{md_text(row.paradigm)} at {md_text(threshold)} does not separate rankings on "
            f"{md_text(row.dataset)}**: no ground truth is distinguishable from the baseline "
            f"({md_text(row.pairs)}), so where a descriptor lies between them says nothing about it there."
        )
    return lines
