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

import html
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
from omegaconf import OmegaConf

from locretrieval.report.html import with_script_policy, write_html
from locretrieval.report.markdown import markdown_table, md_code, md_link, md_text
from locretrieval.training.objective import Objective, run_objective
from locretrieval.training.sweeps import FINISHED_FILE, finished_job, job_folders, job_overrides, trial_overrides

#: What Hydra's sweepers write at the top of a sweep folder (the resumable Optuna sweeper too).
MULTIRUN_FILE = "multirun.yaml"
#: The files of the summary in its folder.
FILES = {"csv": "summary.csv", "markdown": "summary.md", "html": "summary.html", "figures": "optuna.html"}
#: The values of a gap row (``gap.csv``) after the baseline's, whose column is named after ``report.baseline``.
GAP_VALUES = ("untrained", "trained", "groundtruth_value")
#: ``gap.csv``'s columns other than the baseline's.
GAP_COLUMNS = ("metric", *GAP_VALUES, "groundtruth", "gap_closed_pct")


@dataclass
class TrialRow:
    """One trial: its ``label`` (the job's or trial's number, or a run folder's name), the run
    ``folder`` (None: none), ``state`` (``finished``/``not finished``, or Optuna's state in lower
    case), ``objective`` (None: ``note`` says why), ``overrides``, ``seconds`` and ``gap`` (its ``gap.csv``)."""

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
    """The Optuna study of a sweep folder: its ``name``, ``storage`` URL, ``direction`` and ``trials``."""

    name: str
    storage: str
    direction: str
    trials: list[Any]
    optuna_study: Any = field(repr=False)

    def complete(self) -> list[Any]:
        return [trial for trial in self.trials if trial.state.name == "COMPLETE"]


@dataclass
class Summary:
    """The ``rows`` of the summarised ``folders``, the `Objective` they ran with (None: unknown),
    whether it is maximized, and their Optuna ``studies``."""

    rows: list[TrialRow]
    objective: Objective | None
    maximize: bool
    studies: list[Study]
    folders: list[Path]

    def best(self) -> TrialRow | None:
        """The row of the best finite objective (the first of equals), None without one."""
        scored = [row for row in self.rows if row.objective is not None and math.isfinite(row.objective)]
        return (max if self.maximize else min)(scored, key=lambda row: row.objective) if scored else None


def is_training_folder(path: Path) -> bool:
    """Whether ``path`` is a train.py run (``validation.csv``) or a train.py multirun (`MULTIRUN_FILE`)."""
    if (path / "validation.csv").is_file():
        return True
    multirun = path / MULTIRUN_FILE
    return multirun.is_file() and OmegaConf.load(multirun).hydra.job.name == "train"


def summarize(paths: Sequence[Path]) -> Summary:
    """The `Summary` of train.py runs and multiruns (`is_training_folder`); with several folders a
    multirun's labels start with its folder's name."""
    rows: list[TrialRow] = []
    studies: list[Study] = []
    for path in paths:
        if not is_training_folder(path):
            raise FileNotFoundError(f"{path}: neither a train.py run (validation.csv) nor a train.py multirun")
        if (path / MULTIRUN_FILE).is_file():
            study = stored_study(path)
            rows += multirun_rows(path, study, prefix=f"{path.name}/" if len(paths) > 1 else "")
            studies += [study] if study is not None else []
        else:
            rows.append(run_row(path, path.name, job_overrides(path)))
    configs = [row.folder / "config.yaml" for row in rows if row.folder is not None]
    config = next((OmegaConf.load(path) for path in configs if path.is_file()), None)
    objective = Objective.from_config(config) if config is not None and "optimized_metric" in config else None
    maximize = all(study.direction == "maximize" for study in studies)
    return Summary(rows, objective, maximize, studies, list(paths))


def run_row(folder: Path, label: str, overrides: list[str]) -> TrialRow:
    """The row of a train.py run: finished (`finished_job`) with its objective, time and gap rows, or why not."""
    if not finished_job(folder):
        return TrialRow(label, folder, "not finished", None, overrides, note=f"no {FINISHED_FILE}: it did not finish")
    seconds = json.loads((folder / FINISHED_FILE).read_text()).get("seconds")
    gap = pd.read_csv(folder / "gap.csv") if (folder / "gap.csv").is_file() else None
    row = TrialRow(label, folder, "finished", None, overrides, seconds, gap)
    try:
        row.objective = run_objective(folder)
    except (OSError, ValueError) as error:
        row.note = f"no objective: {error}"
    return row


def multirun_rows(folder: Path, study: Study | None, prefix: str) -> list[TrialRow]:
    """The rows of a multirun: one per job, or with a ``study`` one per trial (its state and the
    value the sweeper was told; its job is the folder of its number, `resume_study`)."""
    jobs = job_folders(folder)
    if study is None:
        return [run_row(job, f"{prefix}{number}", job_overrides(job)) for number, job in sorted(jobs.items())]
    rows = []
    for trial in study.trials:
        job = jobs.get(trial.number)
        if job is not None and not set(trial_overrides(trial.params)) <= set(job_overrides(job)):
            job = None  # the folder of a job of another study
        retry = next((t.number for t in study.trials if t.number > trial.number and t.params == trial.params), None)
        rows.append(study_row(trial, job, f"{prefix}{trial.number}", retry))
    return rows


def study_row(trial: Any, job: Path | None, label: str, retry: int | None) -> TrialRow:
    """The row of an Optuna ``trial`` run in ``job`` (None: no folder); ``retry``: the trial that
    ran its parameters again after it was interrupted."""
    overrides = job_overrides(job) if job is not None else trial_overrides(trial.params)
    row = run_row(job, label, overrides) if job is not None else TrialRow(label, None, "", None, overrides)
    row.state, row.objective = trial.state.name.lower(), trial.value
    if trial.user_attrs.get("interrupted"):
        row.note = "interrupted when the sweep was killed" + (
            f"; run again as trial {retry}" if retry is not None else ""
        )
    elif trial.user_attrs.get("recovered"):
        row.note = f"finished before the sweep was killed; its objective {trial.user_attrs['recovered']}"
    elif row.state == "fail":
        row.note = "failed" + (f": see {job.name}/train.log" if job is not None else "")
    elif row.state in ("running", "waiting"):
        row.note = f"{row.state} when the sweep stopped: rerun its command to go on"
    elif job is None:
        row.note = "no job folder"
    return row


def stored_study(folder: Path) -> Study | None:
    """The Optuna study of a sweep folder (its `MULTIRUN_FILE`'s ``hydra.sweeper``: ``storage``,
    ``study_name``); a SQLite file of that name inside the folder is read there (a moved folder
    keeps its study). None for another sweeper or a study kept in memory."""
    sweeper = OmegaConf.load(folder / MULTIRUN_FILE).hydra.sweeper
    if "optuna" not in str(sweeper.get("_target_", "")).lower() or sweeper.get("storage") is None:
        return None
    import optuna

    storage = str(OmegaConf.to_container(sweeper, resolve=False)["storage"])
    inside = folder / Path(storage).name
    if storage.startswith("sqlite:///") and inside.is_file():
        storage = f"sqlite:///{inside.resolve()}"
    study = optuna.load_study(study_name=str(sweeper.study_name), storage=storage)
    return Study(study.study_name, storage, study.direction.name.lower(), study.get_trials(deepcopy=False), study)


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
            "Parameter importances (Optuna's mean decrease in impurity of a random forest fitted to the finished "
            "trials):",
            "",
            markdown_table(importances.to_frame().reset_index(), index=False, floatfmt=".3f"),
        ]
    if write_study_figures(study, importances is not None, output_dir / FILES["figures"]):
        shown = "optimization history" + (" and parameter importances" if importances is not None else "")
        lines += ["", f"The study's {shown}, Optuna's figures: {md_link(FILES['figures'], FILES['figures'])}."]
    return lines + [""]


def parameter_importances(study: Study) -> tuple[pd.Series | None, str]:
    """The importances of the parameters, or None and why there are none. Optuna's seeded
    ``MeanDecreaseImpurityImportanceEvaluator``: its default, fANOVA, fails on the trees of the
    scikit-learn installed here under optuna 2.10 (the version hydra-optuna-sweeper supports)."""
    from optuna.importance import MeanDecreaseImpurityImportanceEvaluator, get_param_importances

    complete = study.complete()
    if len(complete) < 2:
        return None, f"they need 2 finished trials, the study has {len(complete)}"
    if len({trial.value for trial in complete}) < 2:
        return None, f"the objective took one value ({complete[0].value:.4g}) over the finished trials"
    importances = get_param_importances(study.optuna_study, evaluator=MeanDecreaseImpurityImportanceEvaluator(seed=0))
    return pd.Series(importances, name="importance").rename_axis("parameter"), ""


def write_study_figures(study: Study, with_importances: bool, path: Path) -> Path | None:
    """``optuna.html``: Optuna's optimization history (and parameter importances) of ``study``,
    plotly.js embedded once, nothing fetched, its own scripts only (`with_script_policy`); None (no
    file) without a finished trial."""
    import optuna.visualization as visualization
    from optuna.importance import MeanDecreaseImpurityImportanceEvaluator

    if not study.complete():
        return None
    figures = [visualization.plot_optimization_history(study.optuna_study)]
    if with_importances:
        evaluator = MeanDecreaseImpurityImportanceEvaluator(seed=0)
        figures.append(visualization.plot_param_importances(study.optuna_study, evaluator=evaluator))
    parts = [figure.to_html(full_html=False, include_plotlyjs=index == 0) for index, figure in enumerate(figures)]
    title = html.escape(f"Optuna study {study.name}")
    page = f'<!DOCTYPE html>\n<html lang="en">\n<head><meta charset="utf-8"><title>{title}</title></head>\n<body>\n'
    page += f"<h1>{title}</h1>\n" + "\n".join(parts) + "\n</body>\n</html>\n"
    path.write_text(with_script_policy(page), encoding="utf-8")  # its own scripts only: names are data
    return path


def write_summary(paths: Sequence[Path], output_dir: Path) -> Path:
    """Write ``summary.csv``, ``summary.md``, ``summary.html`` (and ``optuna.html`` for a study)
    of the train.py runs and multiruns ``paths`` into ``output_dir``; returns ``summary.md``'s path."""
    output_dir = Path(output_dir)
    output_dir.mkdir(parents=True, exist_ok=True)
    summary = summarize([Path(path) for path in paths])
    trial_table(summary).to_csv(output_dir / FILES["csv"], index=False)
    markdown = output_dir / FILES["markdown"]
    markdown.write_text("\n".join(markdown_lines(summary, output_dir)).rstrip() + "\n")
    write_html(markdown, output_dir / FILES["html"])
    return markdown
