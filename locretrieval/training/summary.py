"""One summary of train.py runs: a sweep's jobs (a grid or an Optuna study) or separate runs.

A table with one row per trial: its overrides (those not shared by every trial), the objective
(``optimized_metric``), each gap row of its training report (``gap.csv``: the baseline, untrained,
trained and ground-truth % localized, and the share of the gap closed), its time, the best trial
marked; with several trials a mean row whose gap is the gap of the means. Where a value is
undefined its cell says why, never ``nan``. For an Optuna study also its optimization history and
parameter importances. Written as ``summary.csv``, ``summary.md``, ``summary.html`` (the page of
the report) and, for a study, ``optuna.html`` (Optuna's plotly figures, plotly.js embedded).
"""

from __future__ import annotations

import csv
import html
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from locretrieval.errors import DataFileError
from locretrieval.report.html import with_script_policy, write_html
from locretrieval.report.markdown import markdown_table, md_code, md_link, md_text
from locretrieval.training.folders import (
    CONFIG_FILE,
    FAILURE,
    FINISHED_FILE,
    GAP_FILE,
    INTERRUPTED,
    MULTIRUN_FILE,
    RETRY_OF,
    finished_job,
    interrupted,
    is_training_folder,
    job_folders,
    job_overrides,
    load_named_study,
    open_study,
    read_as_written,
    run_objective,
    study_file,
    trial_job,
    trial_note,
    trial_overrides,
    written_value,
)
from locretrieval.training.objective import Objective

#: The files of the summary in its folder.
FILES = {"csv": "summary.csv", "markdown": "summary.md", "html": "summary.html", "figures": "optuna.html"}
#: The values of a gap row (``gap.csv``) after the baseline's, whose column is named after ``report.baseline``.
GAP_VALUES = ("untrained", "trained", "groundtruth_value")
#: ``gap.csv``'s columns other than the baseline's.
GAP_COLUMNS = ("metric", *GAP_VALUES, "groundtruth", "gap_closed_pct")
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

    def best(self) -> TrialRow | None:
        """The row of the best finite objective (the first of equals), None without one."""
        scored = [row for row in self.rows if row.objective is not None and math.isfinite(row.objective)]
        return (max if self.maximize else min)(scored, key=lambda row: row.objective) if scored else None


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
    config = next((read_as_written(path) for path in configs if path.is_file()), None)
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
        row.objective = run_objective(folder)
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


def gap_text(reference: float, trained: float, truth: float, baseline: str) -> str:
    """The share of the gap between ``baseline`` and the ground truth that training closed, or why it is undefined."""
    if pd.isna(reference):
        return f"gap undefined: no {baseline} value"
    if pd.isna(truth):
        return "gap undefined: no ground truth validated"
    if truth == reference:
        return f"gap undefined: the ground truth equals {baseline}"
    return f"{100 * (trained - reference) / (truth - reference):.0f} %"


def gap_cell(values: pd.Series, baseline: str) -> str:
    """``baseline / untrained / trained / ground truth (gap closed %)`` of a gap row, % localized."""
    shown = [values[baseline], *(values[name] for name in GAP_VALUES)]
    text = " / ".join("–" if pd.isna(value) else f"{value:.1f}" for value in shown)
    return f"{text} ({gap_text(values[baseline], values['trained'], values['groundtruth_value'], baseline)})"


def gap_baseline(rows: Sequence[TrialRow]) -> str:
    """The baseline of the rows' gap tables (``report.baseline``); `ValueError` when they differ."""
    tables = [row.gap for row in rows if row.gap is not None]
    baselines = sorted({column for table in tables for column in table.columns if column not in GAP_COLUMNS})
    if len(baselines) > 1:
        raise ValueError(f"gap.csv: the runs measure their gap from different baselines {baselines} (report.baseline)")
    return baselines[0] if baselines else "baseline"


def gap_cells(rows: Sequence[TrialRow], baseline: str) -> pd.DataFrame:
    """One cell (`gap_cell`) per trial and gap metric, in the runs' order; a metric a finished run
    has no row for was not validated before and after training; with several runs a last row, the
    means over them and the gap closed of the means."""
    tables = {row.label: row.gap.set_index("metric") for row in rows if row.gap is not None}
    metrics = list(dict.fromkeys(metric for table in tables.values() for metric in table.index))
    cells = pd.DataFrame(index=[row.label for row in rows], columns=metrics, dtype=object)
    for row in rows:
        table = tables.get(row.label)
        for metric in metrics:
            if table is None:
                cells.loc[row.label, metric] = "–"
            elif metric in table.index:
                cells.loc[row.label, metric] = gap_cell(table.loc[metric], baseline)
            else:
                cells.loc[row.label, metric] = "not validated before and after training"
    if len(tables) > 1:
        stacked = pd.concat(tables.values())
        means = stacked[[baseline, *GAP_VALUES]].groupby(level=0).mean()
        cells.loc[f"mean of {len(tables)}"] = [gap_cell(means.loc[metric], baseline) for metric in metrics]
    return cells


def trial_table(summary: Summary) -> pd.DataFrame:
    """``summary.csv``: a row per trial (trial, state, best, objective, seconds, overrides,
    folder, note) with each gap row's values (``<metric> <value>``; empty where undefined, and
    ``<metric> why`` says why)."""
    best, baseline = summary.best(), gap_baseline(summary.rows)
    records = []
    for row in summary.rows:
        record = {
            "trial": row.label,
            "state": row.state,
            "best": row is best,
            "objective": row.objective,
            "seconds": row.seconds,
            "overrides": " ".join(row.overrides),
            "folder": str(row.folder.resolve()) if row.folder is not None else "",
            "note": row.note,
        }
        for metric, values in row.gap.set_index("metric").iterrows() if row.gap is not None else []:
            for name in (baseline, *GAP_VALUES, "gap_closed_pct"):
                record[f"{metric} {name}"] = values[name] if math.isfinite(values[name]) else None
            if not math.isfinite(values["gap_closed_pct"]):
                record[f"{metric} why"] = gap_text(
                    values[baseline], values["trained"], values["groundtruth_value"], baseline
                )
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
            "objective": ["–" if row.objective is None else f"{row.objective:.4g}" for row in summary.rows],
            **{metric: list(cells.loc[labels, metric]) for metric in cells.columns},
            "time": ["–" if row.seconds is None else f"{row.seconds:.0f} s" for row in summary.rows],
            "note": [row.note for row in summary.rows],
        }
    )
    for label in cells.index[len(labels) :]:  # the mean row
        mean = dict.fromkeys(table.columns, "") | {"trial": label} | cells.loc[label].to_dict()
        table = pd.concat([table, pd.DataFrame([mean])], ignore_index=True)
    return table if any(row.note for row in summary.rows) else table.drop(columns="note")


def markdown_lines(summary: Summary, output_dir: Path) -> list[str]:
    """``summary.md``: what was summarised, the trial table and each Optuna study's section."""
    objective, best = summary.objective, summary.best()
    baseline = gap_baseline(summary.rows)
    aim = "higher is better" if summary.maximize else "lower is better"
    shared = shared_overrides(summary.rows)
    objective_text = (
        f"{md_code(objective.metric)} at its {objective.validation} validation after training, {aim}"
        if objective
        else "unknown"
    )
    lines = [
        f"# Sweep summary: {md_text(', '.join(folder.name for folder in summary.folders))}",
        "",
        f"- **folders**: {', '.join(md_code(folder) for folder in summary.folders)}",
        f"- **trials**: {len(summary.rows)}",
        f"- **objective**: {objective_text}",
        f"- **overrides of every trial**: {', '.join(md_code(item) for item in shared) or 'none'}",
        f"- **best trial**: {md_text(best.label)}, objective {best.objective:.4g}"
        if best
        else "- **best trial**: none",
        *(f"- **study not read**: {md_text(why)}" for why in summary.unread),
        "",
        "## Trials",
        "",
        f"Per gap row of the training report: {md_text(baseline)} / untrained / trained / ground truth, % of the "
        f"validation queries localized, and the share of the gap between {md_text(baseline)} and the ground truth "
        "that training closed; for several trials their mean and the gap of the means.",
        "",
        markdown_table(trial_markdown(summary), index=False),
        "",
    ]
    for study in summary.studies:
        lines += study_lines(study, output_dir)
    return lines


def study_lines(study: Study, output_dir: Path) -> list[str]:
    """An Optuna study's section: its trials per state, its best trial, the parameter importances
    and a link to ``optuna.html`` (`write_study_figures`)."""
    states = pd.Series([trial.state.name.lower() for trial in study.trials]).value_counts()
    lines = [
        f"## Optuna study {md_code(study.name)}",
        "",
        f"- **storage**: {md_code(study.storage)}",
        f"- **trials**: {', '.join(f'{count} {state}' for state, count in states.items()) or 'none'}",
        f"- **direction**: {study.direction}",
    ]
    if study.complete():
        best = study.optuna_study.best_trial
        lines.append(f"- **best trial**: {best.number}, value {best.value:.4g}")
    importances, why = parameter_importances(study)
    if importances is None:
        lines += ["", f"No parameter importances: {why}."]
    else:
        lines += [
            "",
            "Parameter importances (Optuna's fANOVA: the share of the objective's variance each parameter explains "
            "in a random forest fitted to the completed trials):",
            "",
            markdown_table(importances.to_frame().reset_index(), index=False, floatfmt=".3f"),
        ]
    if write_study_figures(study, importances is not None, output_dir / FILES["figures"]):
        shown = "optimization history" + (" and parameter importances" if importances is not None else "")
        lines += ["", f"The study's {shown}, Optuna's figures: {md_link(FILES['figures'], FILES['figures'])}."]
    return lines + [""]


def parameter_importances(study: Study) -> tuple[pd.Series | None, str]:
    """The importances of the parameters, or None and why there are none: Optuna's default
    evaluator, fANOVA, seeded (`importance_evaluator`)."""
    from optuna.importance import get_param_importances

    complete = study.complete()
    if len(complete) < 2:
        return None, f"they need 2 finished trials, the study has {len(complete)}"
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
    """``optuna.html``: Optuna's optimization history (and parameter importances) of ``study``,
    plotly.js embedded once, nothing fetched, its own scripts only (`with_script_policy`); None (no
    file) without a finished trial."""
    import optuna.visualization as visualization

    if not study.complete():
        return None
    figures = [visualization.plot_optimization_history(study.optuna_study)]
    if with_importances:
        figures.append(visualization.plot_param_importances(study.optuna_study, evaluator=importance_evaluator()))
    parts = [figure.to_html(full_html=False, include_plotlyjs=index == 0) for index, figure in enumerate(figures)]
    title = html.escape(f"Optuna study {study.name}")
    page = f'<!DOCTYPE html>\n<html lang="en">\n<head><meta charset="utf-8"><title>{title}</title></head>\n<body>\n'
    page += f"<h1>{title}</h1>\n" + "\n".join(parts) + "\n</body>\n</html>\n"
    path.write_text(with_script_policy(page), encoding="utf-8")  # its own scripts only: names are data
    return path


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
    markdown = output_dir / FILES["markdown"]
    markdown.write_text("\n".join(markdown_lines(summary, output_dir)).rstrip() + "\n")
    write_html(markdown, output_dir / FILES["html"])
    return markdown
