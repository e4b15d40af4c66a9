"""One summary of train.py runs: a sweep's jobs (a grid or an Optuna study) or separate runs.

A table with one row per trial: its overrides (those not shared by every trial), the objective
(``optimized_metric``) with its interval on the validation queries it selected on, the same metric on
the held-out validation queries at that validation (``training.validation.held_out``: figures no
selection used), each gap row of its training report (``gap.csv``: the baseline, untrained, trained
and ground-truth % localized, and the share of the gap closed where there is a gap), its time, the
best trial marked; with several trials a mean row whose gap is the gap of the means. Whether the
best trial is distinguishable from the next (a paired test on the held-out queries). Where a value
is undefined its cell says why, never ``nan``. For an Optuna study also its optimization history and,
from `MIN_IMPORTANCE_TRIALS` finished trials, parameter importances. Written as ``summary.csv``,
``summary.md``, ``summary.html`` (the page of
the report) and, for a study, ``optuna.html`` (Optuna's plotly figures, plotly.js embedded).
"""

from __future__ import annotations

import csv
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from locretrieval.errors import DataFileError
from locretrieval.metrics.uncertainty import default_uncertainty, paired_difference
from locretrieval.report.html import write_figures_page, write_html
from locretrieval.report.markdown import (
    ReportWriter,
    difference_text,
    interval_text,
    markdown_table,
    md_code,
    md_link,
    md_text,
)
from locretrieval.report.run_files import load_yaml
from locretrieval.report.training_runs import (
    CONFIG_FILE,
    FAILURE,
    FINISHED_FILE,
    GAP_COLUMNS,
    GAP_FILE,
    INTERRUPTED,
    MULTIRUN_FILE,
    RETRY_OF,
    VALIDATION_QUERIES_FILE,
    finished_job,
    interrupted,
    is_training_folder,
    job_folders,
    job_overrides,
    load_named_study,
    open_study,
    run_objective_figures,
    study_file,
    trial_job,
    trial_note,
    trial_overrides,
    written_value,
)
from locretrieval.training.objective import Objective, ObjectiveFigures

#: The files of the summary in its folder.
FILES = {"csv": "summary.csv", "markdown": "summary.md", "html": "summary.html", "figures": "optuna.html"}
#: The values of a gap row (``gap.csv``) after the baseline's, whose column is named after ``report.baseline``.
GAP_VALUES = ("untrained", "trained", "groundtruth_value")
#: Finished trials below which parameter importances (a random forest fitted to the trials) are noise.
MIN_IMPORTANCE_TRIALS = 10
#: How a CSV cell that a spreadsheet runs as a formula starts (OWASP, "CSV Injection").
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


@dataclass
class TrialRow:
    """One trial: its ``label`` (the job's or trial's number, or a run folder's name), the run
    ``folder`` (None: none), ``state`` (``finished``/``not finished``, or Optuna's state in lower
    case, a failed trial's with its reason: ``fail: <why>``), ``objective`` (None: ``note`` says
    why), ``overrides`` (as written), ``seconds`` and ``gap`` (its ``gap.csv``)."""

    label: str
    folder: Path | None
    state: str
    objective: float | None
    overrides: list[str]
    seconds: float | None = None
    gap: pd.DataFrame | None = None
    note: str = ""
    figures: ObjectiveFigures | None = None  # the objective's interval and held-out figure, when read


@dataclass
class Study:
    """The Optuna study of a sweep folder: its ``name``, ``storage`` (where it was read), ``direction``,
    ``trials`` and the notes of its trials (the study's user attributes, `trial_note`)."""

    name: str
    storage: str
    direction: str
    trials: list[Any]
    optuna_study: Any = field(repr=False)
    notes: dict[str, Any] = field(default_factory=dict, repr=False)

    def complete(self) -> list[Any]:
        return [trial for trial in self.trials if trial.state.name == "COMPLETE"]


@dataclass
class Summary:
    """The ``rows`` of the summarised ``folders``, the `Objective` they ran with (None: unknown),
    whether it is maximized, their Optuna ``studies`` and why a sweep's study was not read (``unread``)."""

    rows: list[TrialRow]
    objective: Objective | None
    maximize: bool
    studies: list[Study]
    folders: list[Path]
    unread: list[str] = field(default_factory=list)

    def ranked(self) -> list[TrialRow]:
        """The rows with a finite objective, best first (the first of equals first)."""
        scored = [row for row in self.rows if row.objective is not None and math.isfinite(row.objective)]
        return sorted(scored, key=lambda row: -row.objective if self.maximize else row.objective)

    def best(self) -> TrialRow | None:
        """The row of the best finite objective (the first of equals), None without one."""
        ranked = self.ranked()
        return ranked[0] if ranked else None


def summarize(paths: Sequence[Path], storage: str | None = None) -> Summary:
    """The `Summary` of train.py runs and multiruns (`is_training_folder`); with several folders a
    multirun's labels start with its folder's name. ``storage``: the study's storage URL of the one
    sweep folder where it is not a file inside it (the running sweep's, named on its command line)."""
    rows: list[TrialRow] = []
    studies: list[Study] = []
    unread: list[str] = []
    for path in paths:
        if not is_training_folder(path):
            raise FileNotFoundError(f"{path}: neither a train.py run (validation.csv) nor a train.py multirun")
        if (path / MULTIRUN_FILE).is_file():
            study, why = stored_study(path, storage if len(paths) == 1 else None)
            rows += multirun_rows(path, study, prefix=f"{path.name}/" if len(paths) > 1 else "")
            studies += [study] if study is not None else []
            unread += [f"{path.name}: {why}"] if why else []
        else:
            rows.append(run_row(path, path.name, job_overrides(path)))
    configs = [row.folder / CONFIG_FILE for row in rows if row.folder is not None]
    config = next((load_yaml(path) for path in configs if path.is_file()), None)
    known = isinstance(config, dict) and {"optimized_metric", "optimized_validation"} <= set(config)
    objective = Objective.from_config(config) if known else None
    maximize = all(study.direction == "maximize" for study in studies)
    return Summary(rows, objective, maximize, studies, list(paths), unread)


def run_row(folder: Path, label: str, overrides: list[str]) -> TrialRow:
    """The row of a train.py run: finished (`finished_job`) with its objective, time and gap rows, or why not."""
    if not finished_job(folder):
        return TrialRow(label, folder, "not finished", None, overrides, note=f"no {FINISHED_FILE}: it did not finish")
    seconds = json.loads((folder / FINISHED_FILE).read_text()).get("seconds")
    gap = pd.read_csv(folder / GAP_FILE) if (folder / GAP_FILE).is_file() else None
    row = TrialRow(
        label, folder, "finished", None, overrides, seconds if isinstance(seconds, (int, float)) else None, gap
    )
    try:
        row.figures = run_objective_figures(folder)
        row.objective = row.figures.value
    except (OSError, ValueError) as error:
        row.note = f"no objective: {error}"
    return row


def multirun_rows(folder: Path, study: Study | None, prefix: str) -> list[TrialRow]:
    """The rows of a multirun: one per job, or with a ``study`` one per trial (its state and the
    value the sweeper was told; its job is the folder of its number, `trial_job`)."""
    jobs = job_folders(folder)
    if study is None:
        return [run_row(job, f"{prefix}{number}", job_overrides(job)) for number, job in sorted(jobs.items())]
    retries = {trial.user_attrs.get(RETRY_OF): trial.number for trial in study.trials}
    return [
        study_row(study, trial, trial_job(trial, jobs), f"{prefix}{trial.number}", retries.get(trial.number))
        for trial in study.trials
    ]


def study_row(study: Study, trial: Any, job: Path | None, label: str, retry: int | None) -> TrialRow:
    """The row of an Optuna ``trial`` run in ``job`` (None: no folder); ``retry``: the trial that
    ran its parameters again. A failed trial's state says why it failed."""
    overrides = job_overrides(job) if job is not None else trial_overrides(trial.params)
    row = run_row(job, label, overrides) if job is not None else TrialRow(label, None, "", None, overrides)
    row.state, row.objective = trial.state.name.lower(), trial.value
    note = trial_note(study.notes, trial.number)
    notes = [f"runs again the parameters of trial {trial.user_attrs[RETRY_OF]}"] if RETRY_OF in trial.user_attrs else []
    if row.state == "fail":
        reason = trial.user_attrs.get(FAILURE) or (INTERRUPTED if interrupted(study.notes, trial) else None)
        row.state = f"fail: {reason or 'no reason recorded'}"
        if retry is not None:
            notes.append(f"run again as trial {retry}")
        elif note.get("not_retried"):
            notes.append(f"not run again: {note['not_retried']}")
        if job is not None:
            notes.append(f"its log: {job.name}/train.log")
    elif note.get("recovered"):
        notes.append(f"finished before the sweep was killed; its objective {note['recovered']}")
    elif row.state in ("running", "waiting"):
        notes.append(f"{row.state} when the sweep stopped: rerun its command to go on")
    elif job is None:
        notes.append("no job folder")
    row.note = "; ".join(notes)
    return row


def stored_study(folder: Path, storage: str | None = None) -> tuple[Study | None, str]:
    """The Optuna study of a sweep folder, from its file in the folder (`study_file`, opened
    read-only) or from ``storage`` (a URL the running sweep was given on its command line);
    ``(None, why)`` when there is none or it cannot be read."""
    study_name = written_value(folder / MULTIRUN_FILE, "hydra.sweeper.study_name")
    try:
        if storage is not None:
            study, where = load_named_study(storage, study_name), storage
        else:
            path, why = study_file(folder)
            if path is None:
                return None, why if why != "not an Optuna sweep" else ""
            study, where = open_study(path, study_name), str(path)
    except (DataFileError, RuntimeError, OSError, ValueError, LookupError) as error:  # e.g. an older Optuna's schema
        return None, f"its Optuna study could not be read: {error}"
    trials = study.get_trials(deepcopy=False)
    return Study(study.study_name, where, study.direction.name.lower(), trials, study, study.user_attrs), ""


def gap_text(values: pd.Series) -> str:
    """The share of the gap closed with its interval (``48 % (12 to 85)``), or why there is none
    (``gap.csv``'s ``gap_note``; a run of an earlier version, which had no test, says so)."""
    note = values.get("gap_note")
    if isinstance(note, str) and note:
        return note
    closed = values.get("gap_closed_pct", math.nan)
    if "gap_note" not in values.index:
        return "gap undefined: a run of an earlier version (no per-query outcomes to test the gap)"
    if pd.isna(closed):
        return "gap undefined"
    low, high = values.get("gap_closed_low_pct", math.nan), values.get("gap_closed_high_pct", math.nan)
    interval = f" ({low:.0f} to {high:.0f})" if not (pd.isna(low) or pd.isna(high)) else ""
    return f"{closed:.0f} %{interval}"


def gap_cell(values: pd.Series, baseline: str) -> str:
    """``baseline / untrained / trained / ground truth (gap closed)`` of a gap row, % localized."""
    shown = [values[baseline], *(values[name] for name in GAP_VALUES)]
    text = " / ".join("–" if pd.isna(value) else f"{value:.1f}" for value in shown)
    return f"{text} ({gap_text(values)})"


def gap_baseline(rows: Sequence[TrialRow]) -> str:
    """The baseline of the rows' gap tables (``report.baseline``); `ValueError` when they differ."""
    known = {*GAP_COLUMNS, *GAP_VALUES}
    tables = [row.gap for row in rows if row.gap is not None]
    baselines = sorted({column for table in tables for column in table.columns if column not in known})
    if len(baselines) > 1:
        raise ValueError(f"gap.csv: the runs measure their gap from different baselines {baselines} (report.baseline)")
    return baselines[0] if baselines else "baseline"


def mean_gap_cell(tables: Sequence[pd.DataFrame], metric: str, baseline: str) -> str:
    """The mean row's cell: the means over the runs of the baseline, untrained, trained and ground
    truth, and the gap of the means where every run has a gap (no interval: the runs' queries differ)."""
    rows = [table.loc[metric] for table in tables if metric in table.index]
    means = pd.DataFrame(rows)[[baseline, *GAP_VALUES]].mean()
    text = " / ".join("–" if pd.isna(value) else f"{value:.1f}" for value in means)
    without = sum(pd.isna(row.get("gap_closed_pct", math.nan)) for row in rows)
    if without:
        return f"{text} (no gap of the means: {without} of {len(rows)} runs have no gap to close)"
    closed = 100 * (means["trained"] - means[baseline]) / (means["groundtruth_value"] - means[baseline])
    return f"{text} (gap of the means {closed:.0f} %; no interval: the runs' queries differ)"


def gap_cells(rows: Sequence[TrialRow], baseline: str) -> pd.DataFrame:
    """One cell (`gap_cell`) per trial and gap metric, in the runs' order; a metric a finished run
    has no row for was not validated before and after training; with several runs a last row
    (`mean_gap_cell`)."""
    tables = {row.label: row.gap.set_index("metric") for row in rows if row.gap is not None}
    metrics = list(dict.fromkeys(metric for table in tables.values() for metric in table.index))
    cells = pd.DataFrame(index=[row.label for row in rows], columns=metrics, dtype=object)
    for row in rows:
        table = tables.get(row.label)
        for metric in metrics:
            if table is None:
                cells.loc[row.label, metric] = "no gap.csv: the run did not finish"
            elif metric in table.index:
                cells.loc[row.label, metric] = gap_cell(table.loc[metric], baseline)
            else:
                cells.loc[row.label, metric] = "not validated before and after training"
    if len(tables) > 1:
        cells.loc[f"mean of {len(tables)}"] = [mean_gap_cell(list(tables.values()), m, baseline) for m in metrics]
    return cells


def objective_text(figures: ObjectiveFigures | None) -> str:
    """The objective with its interval, its number of queries and its validation's epoch."""
    if figures is None:
        return "–"
    text = interval_text(figures.value, figures.low, figures.high)
    queries = f", {figures.num_queries:.0f} queries" if not pd.isna(figures.num_queries) else ""
    return f"{text}{queries}, epoch {figures.epoch}"


def held_out_text(figures: ObjectiveFigures | None) -> str:
    """The objective's metric on the held-out queries at the chosen validation, or why there is none."""
    if figures is None:
        return "–"
    if figures.held_out is None:
        return "no held-out queries (training.validation.held_out=0): only the selection's figure"
    value, low, high, count = figures.held_out
    return f"{interval_text(value, low, high)}, {count:.0f} queries"


def best_against_next(summary: Summary) -> str | None:
    """Whether the best trial is distinguishable from the next: an exact McNemar test on their
    outcomes of the objective's metric at their chosen validations, on the held-out queries (on the
    queries selected on where there are none, which the selection favours), in words; None with
    fewer than two scored trials."""
    ranked = summary.ranked()
    if len(ranked) < 2 or summary.objective is None:
        return None
    best, runner = ranked[0], ranked[1]
    outcomes = [trial_outcomes(row, summary.objective) for row in (best, runner)]
    if any(outcome is None for outcome in outcomes):
        return (
            f"trial {best.label} against trial {runner.label}: not compared (a run without "
            f"{VALIDATION_QUERIES_FILE}, or a retrieval objective, which has no per-query outcome)"
        )
    first, second = outcomes
    split = "held_out" if (first["split"] == "held_out").any() else "val"
    paired = pd.merge(
        first[first["split"] == split], second[second["split"] == split], on="query", suffixes=("_best", "_next")
    )
    if paired.empty:
        return f"trial {best.label} against trial {runner.label}: not compared (no validation query in common)"
    a, b = paired["localized_best"].to_numpy(bool), paired["localized_next"].to_numpy(bool)
    uncertainty = default_uncertainty()
    result = paired_difference(int((a & ~b).sum()), int((~a & b).sum()), len(paired), uncertainty.confidence)
    verdict = "distinguishable" if result.p_value < uncertainty.alpha else "not distinguishable"
    where = (
        f"the {len(paired)} held-out queries"
        if split == "held_out"
        else f"the {len(paired)} queries the sweep selected on (no held-out queries: the selection favours the best)"
    )
    text = difference_text(100 * float(result.difference), 100 * float(result.low), 100 * float(result.high), "")
    return (
        f"trial {best.label} against the next, trial {runner.label}, on {where}: {text.strip()} points "
        f"(exact McNemar p={float(result.p_value):.2g}): {verdict}"
    )


def trial_outcomes(row: TrialRow, objective: Objective) -> pd.DataFrame | None:
    """The per-query outcomes of the objective's metric of a trial at its chosen validation
    (``query, split, localized``), or None where there are none."""
    if row.folder is None or row.figures is None or not (row.folder / VALIDATION_QUERIES_FILE).is_file():
        return None
    table = pd.read_csv(row.folder / VALIDATION_QUERIES_FILE, dtype={"query": str, "split": str})
    key = objective.metric.removeprefix("val/")
    rows = table[(table["ranking"] == "trained") & (table["epoch"] == row.figures.epoch) & (table["metric"] == key)]
    return rows[["query", "split", "localized"]] if len(rows) else None


#: The figures of a gap row that ``summary.csv`` keeps, after the baseline's.
GAP_FIGURES = (*GAP_VALUES, "gap_closed_pct", "gap_closed_low_pct", "gap_closed_high_pct")


def trial_table(summary: Summary) -> pd.DataFrame:
    """``summary.csv``: a row per trial (trial, state, best, objective and its interval, its number of
    queries and epoch, the held-out figure and its interval, seconds, overrides, folder, note) with each
    gap row's values (``<metric> <value>``; empty where undefined, and ``<metric> why`` says why)."""
    best, baseline = summary.best(), gap_baseline(summary.rows)
    records = []
    for row in summary.rows:
        figures = row.figures
        held = figures.held_out if figures is not None and figures.held_out is not None else (None,) * 4
        record = {
            "trial": row.label,
            "state": row.state,
            "best": row is best,
            "objective": row.objective,
            "objective_low": figures.low if figures else None,
            "objective_high": figures.high if figures else None,
            "objective_queries": figures.num_queries if figures else None,
            "objective_epoch": figures.epoch if figures else None,
            "held_out": held[0],
            "held_out_low": held[1],
            "held_out_high": held[2],
            "held_out_queries": held[3],
            "seconds": row.seconds,
            "overrides": " ".join(row.overrides),
            "folder": str(row.folder.resolve()) if row.folder is not None else "",
            "note": row.note,
        }
        for metric, values in row.gap.set_index("metric").iterrows() if row.gap is not None else []:
            for name in (baseline, *GAP_FIGURES):
                value = values.get(name, math.nan)
                record[f"{metric} {name}"] = value if isinstance(value, (int, float)) and math.isfinite(value) else None
            if pd.isna(values.get("gap_closed_pct", math.nan)):
                record[f"{metric} why"] = gap_text(values)
        records.append(record)
    return pd.DataFrame(records)


def shown_override(item: str) -> str:
    """``key=value`` with a long number shortened to 3 significant digits (the CSV keeps it whole)."""
    key, _, value = item.partition("=")
    if re.fullmatch(r"-?\d+\.\d{4,}(e-?\d+)?|-?\d\.\d+e-?\d+", value):
        return f"{key}={float(value):.3g}"
    return item


def shared_overrides(rows: Sequence[TrialRow]) -> list[str]:
    """The overrides every trial has (shown once, above the table)."""
    if len(rows) < 2:
        return []
    shared = set.intersection(*(set(row.overrides) for row in rows))
    return [item for item in rows[0].overrides if item in shared]


def trial_markdown(summary: Summary) -> pd.DataFrame:
    """The trial table of ``summary.md`` (its text escaped by `markdown_table`): the trials (the
    best marked), their overrides not shared by all, objective, gap cells and time, then the mean
    row; the notes when there are any."""
    best, shared = summary.best(), shared_overrides(summary.rows)
    cells = gap_cells(summary.rows, gap_baseline(summary.rows))
    labels = [row.label for row in summary.rows]
    table = pd.DataFrame(
        {
            "trial": [f"{row.label} (best)" if row is best else row.label for row in summary.rows],
            "state": [row.state for row in summary.rows],
            "overrides": [
                ", ".join(shown_override(item) for item in row.overrides if item not in shared) for row in summary.rows
            ],
            "objective (selected on)": [objective_text(row.figures) for row in summary.rows],
            "held out": [held_out_text(row.figures) for row in summary.rows],
            **{metric: list(cells.loc[labels, metric]) for metric in cells.columns},
            "time": ["–" if row.seconds is None else f"{row.seconds:.0f} s" for row in summary.rows],
            "note": [row.note for row in summary.rows],
        }
    )
    for label in cells.index[len(labels) :]:  # the mean row
        mean = dict.fromkeys(table.columns, "") | {"trial": label} | cells.loc[label].to_dict()
        table = pd.concat([table, pd.DataFrame([mean])], ignore_index=True)
    return table if any(row.note for row in summary.rows) else table.drop(columns="note")


def summary_report(summary: Summary, output_dir: Path) -> ReportWriter:
    """``summary.md``: what was summarised, the best trial against the next, the trial table and each
    Optuna study's section (`study_section`)."""
    objective, best = summary.objective, summary.best()
    baseline = gap_baseline(summary.rows)
    aim = "higher is better" if summary.maximize else "lower is better"
    shared = shared_overrides(summary.rows)
    objective_line = (
        f"{md_code(objective.metric)} at its {objective.validation} validation after training, {aim}"
        if objective
        else "unknown"
    )
    against = best_against_next(summary)
    writer = ReportWriter(output_dir, f"Sweep summary: {md_text(', '.join(folder.name for folder in summary.folders))}")
    writer.bullets(
        [
            ("folders", ", ".join(md_code(folder) for folder in summary.folders)),
            ("trials", len(summary.rows)),
            ("objective", objective_line),
            ("overrides of every trial", ", ".join(md_code(item) for item in shared) or "none"),
            (
                "best trial",
                f"{md_text(best.label)}, objective {md_text(objective_text(best.figures))}; held out: "
                f"{md_text(held_out_text(best.figures))}"
                if best
                else "none",
            ),
            *([("best against the next", md_text(against))] if against else []),
            *(("study not read", md_text(why)) for why in summary.unread),
        ]
    )
    writer.heading("Trials")
    writer.text(
        "The objective is measured on the validation queries the sweep selects on (its interval, its queries and "
        "the validation it was taken at): the best trial's figure there is favoured by its own selection. The "
        "held-out column is the same metric at the same validation on the validation queries kept out of every "
        "selection (training.validation.held_out): the figure to report.",
        f"Per gap row of the training report: {md_text(baseline)} / untrained / trained / ground truth, % of the "
        f"held-out validation queries localized (all of them without a held-out share), and the share of the gap "
        f"between {md_text(baseline)} and the ground truth that training closed with its interval, where the ground "
        "truth is distinguishably above the baseline; for several trials their mean and the gap of the means.",
        markdown_table(trial_markdown(summary), index=False),
    )
    for study in summary.studies:
        study_section(writer, study, output_dir)
    return writer


def study_section(writer: ReportWriter, study: Study, output_dir: Path) -> None:
    """An Optuna study's section: its trials per state, its best trial, the parameter importances
    and a link to ``optuna.html`` (`write_study_figures`)."""
    states = pd.Series([trial.state.name.lower() for trial in study.trials]).value_counts()
    writer.heading(f"Optuna study {md_code(study.name)}")
    items = [
        ("storage", md_code(study.storage)),
        ("trials", ", ".join(f"{count} {state}" for state, count in states.items()) or "none"),
        ("direction", study.direction),
    ]
    if study.complete():
        best = study.optuna_study.best_trial
        items.append(("best trial", f"{best.number}, value {best.value:.4g}"))
    writer.bullets(items)
    importances, why = parameter_importances(study)
    if importances is None:
        writer.text(f"No parameter importances: {why}.")
    else:
        writer.text(
            f"Parameter importances over {len(study.complete())} finished trials (Optuna's fANOVA: the share of the "
            "objective's variance each parameter explains in a random forest fitted to them):",
            markdown_table(importances.to_frame().reset_index(), index=False, floatfmt=".3f"),
        )
    if write_study_figures(study, importances is not None, output_dir / FILES["figures"]):
        shown = "optimization history" + (" and parameter importances" if importances is not None else "")
        writer.text(f"The study's {shown}, Optuna's figures: {md_link(FILES['figures'], FILES['figures'])}.")


def parameter_importances(study: Study) -> tuple[pd.Series | None, str]:
    """The importances of the parameters, or None and why there are none: Optuna's default
    evaluator, fANOVA, seeded (`importance_evaluator`)."""
    from optuna.importance import get_param_importances

    complete = study.complete()
    if len(complete) < MIN_IMPORTANCE_TRIALS:
        return None, (
            f"a random forest fitted to {len(complete)} finished trials says nothing; they are computed from "
            f"{MIN_IMPORTANCE_TRIALS} on"
        )
    if len({trial.value for trial in complete}) < 2:
        return None, f"the objective took one value ({complete[0].value:.4g}) over the finished trials"
    importances = get_param_importances(study.optuna_study, evaluator=importance_evaluator())
    return pd.Series(importances, name="importance").rename_axis("parameter"), ""


def importance_evaluator() -> Any:
    """Optuna's fANOVA importance evaluator (its default: a random forest fitted to the completed
    trials, the variance each parameter explains), seeded: the same study gives the same importances."""
    from optuna.importance import FanovaImportanceEvaluator

    return FanovaImportanceEvaluator(seed=0)


def write_study_figures(study: Study, with_importances: bool, path: Path) -> Path | None:
    """``optuna.html``: Optuna's optimization history (and parameter importances) of ``study``
    (`write_figures_page`); None (no file) without a finished trial."""
    import optuna.visualization as visualization

    if not study.complete():
        return None
    figures = [visualization.plot_optimization_history(study.optuna_study)]
    if with_importances:
        figures.append(visualization.plot_param_importances(study.optuna_study, evaluator=importance_evaluator()))
    return write_figures_page(path, f"Optuna study {study.name}", figures)


def spreadsheet_safe(table: pd.DataFrame) -> pd.DataFrame:
    """``table`` with each text cell that a spreadsheet would read as a formula (one starting with
    ``= + - @``, a tab or a carriage return) prefixed by ``'``, as OWASP's CSV injection guidance says;
    numbers are left as they are."""
    return table.map(lambda value: f"'{value}" if isinstance(value, str) and value[:1] in FORMULA_STARTS else value)


def write_summary(paths: Sequence[Path], output_dir: Path, storage: str | None = None) -> Path:
    """Write ``summary.csv``, ``summary.md``, ``summary.html`` (and ``optuna.html`` for a study)
    of the train.py runs and multiruns ``paths`` into ``output_dir`` (`summarize`, its ``storage``);
    returns ``summary.md``'s path. The CSV's text cells are quoted and `spreadsheet_safe`."""
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    summary = summarize([Path(path) for path in paths], storage)
    table = spreadsheet_safe(trial_table(summary))
    table.to_csv(output_dir / FILES["csv"], index=False, quoting=csv.QUOTE_NONNUMERIC)
    markdown = summary_report(summary, output_dir).write(output_dir / FILES["markdown"])
    write_html(markdown, output_dir / FILES["html"])
    return markdown
