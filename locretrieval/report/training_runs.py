"""The files of train.py's run folders and sweep folders, and how they are read.

`locretrieval.training.run` writes a run folder, the sweeper (`locretrieval.training.sweeps`) a sweep
folder of job folders and its Optuna study; the sweeper and the summary
(`locretrieval.report.training_summary`) read both. A folder may be someone else's (a shared sweep):
its YAML files are read as written (`locretrieval.report.run_files.load_yaml`: ``${oc.env:HOME}``
stays text, no resolver runs), a value that must be a number is checked (`DataFileError` naming the
file and key), and its study is opened only from a file inside it, read-only, never created (`open_study`).
"""

from __future__ import annotations

import json
import os
import urllib.parse
from pathlib import Path
from typing import Any

import pandas as pd

from locretrieval.errors import FIX_DATA_FILE, DataFileError
from locretrieval.report.run_files import load_yaml
from locretrieval.training.objective import Objective, ObjectiveFigures

#: A train.py run's composed config (written resolved).
CONFIG_FILE = "config.yaml"
#: A finished train.py run: the file it writes last (rank 0, after its report).
FINISHED_FILE = "summary.json"
#: A train.py run's validations (``epoch, metric, value, low, high, num_queries``).
VALIDATION_FILE = "validation.csv"
#: Each validation query's outcome (``ranking, epoch, metric, query, split, localized``).
VALIDATION_QUERIES_FILE = "validation_queries.csv.gz"
#: A train.py run's gap rows (the training report's table).
GAP_FILE = "gap.csv"
#: ``gap.csv``'s columns; the baseline's value is in one more, named after ``report.baseline``.
GAP_COLUMNS = [
    "metric",
    "split",
    "num_queries",
    "untrained",
    "trained",
    "trained_low",
    "trained_high",
    "baseline_low",
    "baseline_high",
    "groundtruth",
    "groundtruth_value",
    "groundtruth_low",
    "groundtruth_high",
    "gap_pts",
    "gap_low_pts",
    "gap_high_pts",
    "gap_closed_pct",
    "gap_closed_low_pct",
    "gap_closed_high_pct",
    "gap_note",
]
#: A run's checkpoints (``callbacks.*.dirpath`` of configs/callbacks/checkpoints.yaml).
CHECKPOINTS_FOLDER = "checkpoints"
#: What Hydra's sweepers write at the top of a sweep folder (the project's Optuna sweeper too).
MULTIRUN_FILE = "multirun.yaml"
#: A job's command-line overrides and its Hydra config, in the job folder.
OVERRIDES_FILE = Path(".hydra") / "overrides.yaml"
HYDRA_FILE = Path(".hydra") / "hydra.yaml"
#: ``hydra.sweeper.storage``'s names of the study files kept in the sweep folder.
STORAGE_FILES = {"sqlite": "optuna.db", "journal": "optuna.journal"}
#: A trial's user attributes: why it failed; the trial whose parameters it runs again.
FAILURE, RETRY_OF = "failure", "retry_of"
#: How the reason of a trial the sweep left running (killed) reads, told failed when its command is rerun.
INTERRUPTED = "interrupted: the sweep stopped while it ran"
#: How the reason of a trial that was not launched starts (it is not run again).
NOT_RUN = "not run"


def written_value(path: Path, key: str) -> Any:
    """The value at the dotted ``key`` of the YAML file ``path`` as written (`load_yaml`);
    None where the file lacks it."""
    value = load_yaml(path)
    for part in key.split("."):
        value = value.get(part) if isinstance(value, dict) else None
    return value


def finished_job(folder: Path) -> bool:
    """Whether the train.py job in ``folder`` finished: its `FINISHED_FILE` written whole."""
    try:
        json.loads((folder / FINISHED_FILE).read_text())
    except (OSError, ValueError):
        return False
    return True


def job_number(folder: Path) -> int:
    """A job folder's number (``hydra.job.num`` of its `HYDRA_FILE`); `DataFileError` naming the
    file and key when it is not a whole number."""
    path = folder / HYDRA_FILE
    number = written_value(path, "hydra.job.num")
    if isinstance(number, bool) or not isinstance(number, int):
        raise DataFileError(path, f"hydra.job.num: {number!r} is not a job number (a whole number)", FIX_DATA_FILE)
    return number


def job_folders(sweep_dir: Path) -> dict[int, Path]:
    """The job folders of a multirun by job number (`job_number`)."""
    return {job_number(path.parent.parent): path.parent.parent for path in sorted(sweep_dir.glob(f"*/{HYDRA_FILE}"))}


def job_overrides(folder: Path) -> list[str]:
    """A job's command-line overrides (`OVERRIDES_FILE`) as written."""
    path = folder / OVERRIDES_FILE
    overrides = load_yaml(path) if path.is_file() else []
    if not isinstance(overrides, list):
        raise DataFileError(path, f"a list of overrides expected, not {type(overrides).__name__}", FIX_DATA_FILE)
    return [str(item) for item in overrides]


def trial_overrides(params: dict[str, Any]) -> list[str]:
    """A trial's parameters as the sweeper passes them to its job (``key=value``)."""
    return [f"{name}={value}" for name, value in params.items()]


def trial_job(trial: Any, jobs: dict[int, Path]) -> Path | None:
    """The job folder of an Optuna ``trial`` among ``jobs`` (`job_folders`): the one of its number
    whose overrides hold its parameters (None: none, or a job of another study)."""
    job = jobs.get(trial.number)
    if job is None or not set(trial_overrides(trial.params)) <= set(job_overrides(job)):
        return None
    return job


def run_objective(folder: Path) -> float:
    """The objective of the finished train.py run in ``folder``: the `Objective` of the
    `CONFIG_FILE` it wrote (as written), from its `VALIDATION_FILE`; `ValueError` as `Objective.value`."""
    return run_objective_figures(folder).value


def run_objective_figures(folder: Path) -> ObjectiveFigures:
    """`run_objective` with its interval and the held-out figure at its validation (`Objective.figures`)."""
    path = folder / CONFIG_FILE
    config = load_yaml(path)
    if not isinstance(config, dict) or not {"optimized_metric", "optimized_validation"} <= set(config):
        raise DataFileError(path, "not a train.py config: no optimized_metric and optimized_validation")
    return Objective.from_config(config).figures(pd.read_csv(folder / VALIDATION_FILE))


def is_training_folder(path: Path) -> bool:
    """Whether ``path`` is a train.py run (`VALIDATION_FILE`) or a train.py multirun (`MULTIRUN_FILE`)."""
    if (path / VALIDATION_FILE).is_file():
        return True
    multirun = path / MULTIRUN_FILE
    return multirun.is_file() and written_value(multirun, "hydra.job.name") == "train"


def study_file(folder: Path) -> tuple[Path | None, str]:
    """The file of the Optuna study of the sweep ``folder`` (its `MULTIRUN_FILE`'s
    ``hydra.sweeper.storage`` as written): a name of `STORAGE_FILES`, or a SQLite URL whose file
    name is looked up in the folder (a moved folder keeps its study). ``(None, why)`` when there is
    none in the folder: another storage is never opened from a folder's files."""
    sweeper = written_value(folder / MULTIRUN_FILE, "hydra.sweeper")
    if not isinstance(sweeper, dict) or "optuna" not in str(sweeper.get("_target_", "")).lower():
        return None, "not an Optuna sweep"
    storage = sweeper.get("storage")
    if storage is None:
        return None, "its study was kept in memory (hydra.sweeper.storage: null)"
    name = STORAGE_FILES.get(str(storage)) or (
        Path(str(storage)).name if str(storage).startswith("sqlite:///") else None
    )
    path = folder / name if name else None
    if path is None or not path.is_file() or not path.resolve().is_relative_to(folder.resolve()):
        return None, f"its storage {str(storage)!r} is not a file in the sweep folder (only those are read)"
    return path, ""


def open_study(path: Path, study_name: Any = None) -> Any:
    """The Optuna study stored in the file ``path`` (`STORAGE_FILES`: SQLite, or Optuna's journal
    when it ends ``.journal``), opened read-only (`load_named_study`)."""
    from optuna.storages import JournalStorage, RDBStorage
    from optuna.storages.journal import JournalFileBackend

    if path.suffix == Path(STORAGE_FILES["journal"]).suffix:
        storage = JournalStorage(JournalFileBackend(os.fspath(path)))
    else:  # SQLite's read-only mode: nothing is created or written
        url = f"sqlite:///file:{urllib.parse.quote(os.fspath(path.resolve()))}?mode=ro&uri=true"
        storage = RDBStorage(url, skip_table_creation=True)
    return load_named_study(storage, study_name, path)


def load_named_study(storage: Any, study_name: Any, where: Any = None) -> Any:
    """The study ``study_name`` of an Optuna ``storage`` (a URL or a storage), else its only study;
    `DataFileError` naming ``where`` (default: the storage) when neither is there."""
    import optuna

    names = optuna.get_all_study_names(storage)
    if study_name not in names:
        if len(names) != 1:
            raise DataFileError(where or storage, f"no Optuna study {study_name!r} (it holds {names})")
        study_name = names[0]
    return optuna.load_study(study_name=study_name, storage=storage)


def note_key(number: int) -> str:
    """The study's user attribute that notes how a trial of a killed sweep was concluded."""
    return f"trial {number}"


def trial_note(study_attrs: dict[str, Any], number: int) -> dict[str, Any]:
    """The note of trial ``number`` among a study's user attributes ``study_attrs`` (`note_key`:
    ``interrupted``, ``recovered``, ``not_retried``), empty without one. The study's, not the trial's:
    a trial that another process asked cannot take user attributes through Optuna's interface."""
    note = study_attrs.get(note_key(number))
    return note if isinstance(note, dict) else {}


def interrupted(study_attrs: dict[str, Any], trial: Any) -> bool:
    """Whether the failed ``trial`` was interrupted by a kill rather than failed by its job."""
    return bool(trial_note(study_attrs, trial.number).get("interrupted"))
