"""Sweeps of train.py (``-m``): the project's Optuna study (``hparams_search=localization``), run by
the Hydra sweeper ``hydra_plugins.locretrieval_sweeper`` through Optuna's ask-and-tell interface,
resumed and retried by rerunning its command; its search space in Hydra's sweep grammar; the loss
parameters of the localization search; the summary written at the end of every multirun.

Imported by every train.py run (the Hydra callback): the heavy modules only where they are used.
"""

from __future__ import annotations

import logging
import math
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from locretrieval.cli import Mistake
from locretrieval.config import ConfigError, built, require, validated
from locretrieval.report.training_runs import (
    CHECKPOINTS_FOLDER,
    FAILURE,
    MULTIRUN_FILE,
    NOT_RUN,
    RETRY_OF,
    STORAGE_FILES,
    finished_job,
    interrupted,
    job_folders,
    note_key,
    run_objective,
    study_file,
    trial_job,
    trial_note,
    trial_overrides,
)

log = logging.getLogger(__name__)

#: The sweeper's ``_target_`` (configs/hydra/sweeper/optuna.yaml).
SWEEPER = "hydra_plugins.locretrieval_sweeper.resumable_optuna.ResumableOptunaSweeper"


@dataclass
class SweepSettings:
    """``hydra.sweeper`` (configs/hydra/sweeper/optuna.yaml): the ``sampler`` node, the ``direction``
    of the objective, the ``storage`` (`STORAGE_FILES`' names: a file in the sweep folder; an Optuna
    storage URL; None: in memory), ``study_name``, ``n_trials`` completed trials in all, ``n_jobs``
    trials per batch, ``max_failure_rate`` of a batch, ``max_retries`` of a trial that failed,
    ``keep_checkpoints`` (the best trials whose checkpoints stay; None: all), the search space
    (``params``: key -> Hydra sweep) and a ``custom_search_space`` function."""

    sampler: Any
    direction: str
    storage: str | None
    study_name: str
    n_trials: int
    n_jobs: int
    max_failure_rate: float
    max_retries: int
    keep_checkpoints: int | None
    params: dict[str, str] | None
    custom_search_space: str | None

    def __post_init__(self) -> None:
        require(self.direction in ("minimize", "maximize"), "direction", f"{self.direction!r}; minimize or maximize")
        require(self.n_trials >= 0, "n_trials", f"{self.n_trials} < 0")
        require(self.n_jobs >= 1, "n_jobs", f"{self.n_jobs} < 1")
        require(0 <= self.max_failure_rate <= 1, "max_failure_rate", f"{self.max_failure_rate} is not in [0, 1]")
        require(self.max_retries >= 0, "max_retries", f"{self.max_retries} < 0")
        require(self.keep_checkpoints is None or self.keep_checkpoints >= 0, "keep_checkpoints", "null or >= 0")


class SweepStopped(RuntimeError):
    """More trials of a batch failed than ``hydra.sweeper.max_failure_rate`` allows (or all of them)."""


@dataclass
class SearchSpace:
    """What a study draws (``distributions``, Optuna's, by key) and what every trial is given as is
    (``fixed``: the command line's other overrides, key -> the override as written)."""

    distributions: dict[str, Any]
    fixed: dict[str, str]

    @classmethod
    def parse(cls, overrides: Sequence[str]) -> SearchSpace:
        """The search space of Hydra overrides (``key=<sweep>`` or ``key=value``), `distribution` of each sweep."""
        from hydra.core.override_parser.overrides_parser import OverridesParser

        distributions: dict[str, Any] = {}
        fixed: dict[str, str] = {}
        for override in OverridesParser.create().parse_overrides(list(overrides)):  # a later one replaces
            key = override.get_key_element()
            distributions.pop(key, None)
            fixed.pop(key, None)
            if override.is_sweep_override():
                distributions[key] = distribution(override)
            else:
                fixed[key] = override.input_line
        return cls(distributions, fixed)

    def misfit(self, params: dict[str, Any]) -> str | None:
        """Why ``params`` (a trial's) do not fit these distributions (None: they do)."""
        for name, value in params.items():
            if name in self.distributions and (why := outside(self.distributions[name], value)):
                return f"{name}={value} {why}"
        return None


def distribution(override: Any) -> Any:
    """Optuna's distribution of a Hydra sweep override: ``interval(a, b)`` a float in [a, b],
    ``int(interval(a, b))`` an integer, ``tag(log, ...)`` either on a log scale, ``range`` of
    integers an integer with its step (its stop excluded, as Hydra's), ``choice(...)`` and any
    other range (floats, ``shuffle``) a categorical of its values."""
    from hydra.core.override_parser.types import IntervalSweep, RangeSweep, Transformer
    from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution

    sweep = override.value()
    if isinstance(sweep, IntervalSweep):
        log_scale = "log" in sweep.tags
        if isinstance(sweep.start, int) and isinstance(sweep.end, int):
            return IntDistribution(sweep.start, sweep.end, log=log_scale)
        return FloatDistribution(float(sweep.start), float(sweep.end), log=log_scale)
    values = list(override.sweep_iterator(transformer=Transformer.encode))
    if isinstance(sweep, RangeSweep) and not sweep.shuffle and values and all(type(v) is int for v in values):
        return IntDistribution(min(values), max(values), step=abs(sweep.step))
    return CategoricalDistribution(values)


def suggest(trial: Any, name: str, drawn: Any) -> Any:
    """``trial.suggest_*`` of Optuna's distribution ``drawn`` under ``name``."""
    from optuna.distributions import CategoricalDistribution, IntDistribution

    if isinstance(drawn, CategoricalDistribution):
        return trial.suggest_categorical(name, drawn.choices)
    if isinstance(drawn, IntDistribution):
        return trial.suggest_int(name, drawn.low, drawn.high, step=drawn.step, log=drawn.log)
    return trial.suggest_float(name, drawn.low, drawn.high, step=drawn.step, log=drawn.log)


def outside(drawn: Any, value: Any) -> str | None:
    """Why ``value`` is not one that Optuna's distribution ``drawn`` gives (None: it is)."""
    from optuna.distributions import CategoricalDistribution, IntDistribution

    if isinstance(drawn, CategoricalDistribution):
        return None if value in drawn.choices else f"is not among the choices {list(drawn.choices)}"
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not number or (isinstance(drawn, IntDistribution) and value != int(value)):
        kind = "a whole number" if isinstance(drawn, IntDistribution) else "a number"
        return f"is not {kind} in [{drawn.low}, {drawn.high}]"
    return None if drawn.low <= value <= drawn.high else f"is outside [{drawn.low}, {drawn.high}]"


def loss_parameters(cfg: DictConfig, trial: Any) -> None:
    """``hydra.sweeper.custom_search_space`` of ``hparams_search=localization``: the parameters of
    the loss a trial drew (or the ``loss`` fixed on the command line), each drawn from its range
    in ``loss_search_space.<loss>`` (``{key: sweep}`` in Hydra's grammar, `SearchSpace`)."""
    loss = trial.params.get("loss", cfg.hydra.runtime.choices.get("loss"))  # drawn, else the command line's
    ranges = (cfg.get("loss_search_space") or {}).get(loss) or {}
    for name, drawn in SearchSpace.parse([f"{key}={value}" for key, value in ranges.items()]).distributions.items():
        suggest(trial, name, drawn)


class SweepSummary(Callback):
    """``hydra.callbacks.sweep_summary``: at the end of a multirun (a grid or an Optuna study),
    the summary of its jobs in the sweep folder (`write_sweep_summary`)."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        write_sweep_summary(config)


def write_sweep_summary(config: DictConfig) -> Path:
    """`write_summary` of the multirun of ``config`` in its sweep folder; for the project's Optuna
    sweeper, its study from its file in the folder, or from the storage its command line named
    (`study_storage`)."""
    from locretrieval.report.training_summary import write_summary

    folder = Path(config.hydra.sweep.dir)
    storage = study_storage(config) if config.hydra.sweeper.get("_target_") == SWEEPER else None
    named = storage if isinstance(storage, str) and study_file(folder)[0] is None else None  # outside the folder
    markdown = write_summary([folder], folder, storage=named)
    log.info("summary of the sweep: %s", markdown)
    return markdown


def sweep_settings(config: DictConfig) -> SweepSettings:
    """``hydra.sweeper`` of the multirun ``config``, checked (`SweepSettings`)."""
    node = OmegaConf.to_container(config.hydra.sweeper, resolve=True)
    return validated(SweepSettings, {k: v for k, v in node.items() if not k.startswith("_")}, "hydra.sweeper")


def command_line_storage(config: DictConfig) -> bool:
    """Whether the command line itself names ``hydra.sweeper.storage`` (among its Hydra overrides)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    overrides = OverridesParser.create().parse_overrides(list(config.hydra.overrides.hydra))
    return any(override.key_or_group == "hydra.sweeper.storage" for override in overrides)


def study_storage(config: DictConfig) -> Any:
    """The storage of the study of the multirun ``config`` (``hydra.sweeper.storage``): ``sqlite``
    (`STORAGE_FILES`' ``optuna.db`` in the sweep folder), ``journal`` (Optuna's `JournalStorage` in
    a file, ``optuna.journal``, safe on a shared filesystem where SQLite is not), None (in memory), or
    an Optuna storage URL. A storage that is not a file in the sweep folder is used only when the
    command line names it: a folder's files (a shared sweep's ``multirun.yaml``) never make a
    database elsewhere (`ConfigError`)."""
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend

    sweep_dir = Path(config.hydra.sweep.dir)
    storage = config.hydra.sweeper.get("storage")
    if storage is None:
        return None
    if storage == "journal":
        sweep_dir.mkdir(parents=True, exist_ok=True)
        return JournalStorage(JournalFileBackend(str(sweep_dir / STORAGE_FILES["journal"])))
    if storage == "sqlite":
        return f"sqlite:///{(sweep_dir / STORAGE_FILES['sqlite']).resolve()}"
    storage = str(storage)
    database = Path(storage.removeprefix("sqlite:///")) if storage.startswith("sqlite:///") else None
    inside = database is not None and database.resolve().is_relative_to(sweep_dir.resolve())
    if not inside and not command_line_storage(config):
        raise ConfigError(
            f"hydra.sweeper.storage: {storage!r} is not a file in the sweep folder {sweep_dir}; a storage elsewhere "
            "is used only when the command line names it (hydra.sweeper.storage=...); sqlite or journal keep the "
            "study in the sweep folder"
        )
    return storage


def optimize(config: DictConfig, arguments: list[str], launch: Callable[..., Any]) -> None:
    """Run the study of the multirun ``config`` (the sweep's command-line overrides ``arguments``,
    ``launch``: the Hydra launcher's ``launch(overrides, initial_job_idx)``) until
    ``hydra.sweeper.n_trials`` of its trials completed and its failed trials were run again:

    - the sweep folder is made and its config saved there as the basic sweeper saves it
      (`MULTIRUN_FILE`: the summary reads it); a study started by another command is refused;
    - the trials a killed sweep left running are told (`conclude_running_trials`); the failed ones
      are run again once more, up to ``max_retries`` times (`retry_failed_trials`);
    - trials are asked in batches of ``n_jobs``, each drawing ``params`` and the custom search space,
      launched as jobs whose numbers are the trials' numbers, and told their objective or why they
      failed (user attribute `FAILURE`); the checkpoints of all but the best ``keep_checkpoints``
      trials are deleted after each batch;
    - a batch where more than ``max_failure_rate`` of the trials failed (or all of them) stops the
      study (`SweepStopped`, after writing the summary).
    """
    import optuna

    settings = sweep_settings(config)
    sweep_dir = Path(config.hydra.sweep.dir)
    sweep_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(config, sweep_dir / MULTIRUN_FILE)
    space = SearchSpace.parse([f"{key}={value}" for key, value in (settings.params or {}).items()] + arguments)
    storage = study_storage(config)
    study = optuna.create_study(
        study_name=settings.study_name,
        storage=storage,
        sampler=reseeded(settings.sampler, 0),
        direction=settings.direction,
        load_if_exists=True,
    )
    check_same_command(study, arguments, settings.params)
    conclude_running_trials(study, sweep_dir)
    check_same_distributions(study, space)
    retry_failed_trials(study, space, settings.max_retries)
    held = len(study.get_trials(deepcopy=False))
    if held and storage is not None:  # a resumed study: its sampler seeded past the trials it holds
        study = optuna.load_study(
            study_name=study.study_name, storage=storage, sampler=reseeded(settings.sampler, held)
        )
    extend = None  # a function of the multirun's config and a trial, which suggests more parameters
    if settings.custom_search_space:
        node = OmegaConf.create({"_target_": settings.custom_search_space, "_partial_": True})
        extend = built(node, "hydra.sweeper.custom_search_space")
    log.info("study %r: %s", study.study_name, progress(study, settings.n_trials))
    while (to_go := max(settings.n_trials - completed(study), waiting(study))) > 0:
        trials = [study.ask() for _ in range(min(settings.n_jobs, to_go))]
        drawn = [trial for trial in trials if drew(study, trial, space, lambda trial: extend and extend(config, trial))]
        failures = launch_trials(study, drawn, space, launch) + len(trials) - len(drawn)
        keep_best_checkpoints(study, sweep_dir, settings.keep_checkpoints)
        if failures and (failures == len(trials) or failures / len(trials) > settings.max_failure_rate):
            write_sweep_summary(config)
            reasons = [f"trial {t.number}: {t.user_attrs[FAILURE]}" for t in trials if FAILURE in t.user_attrs]
            raise SweepStopped(
                f"{failures} of the {len(trials)} trials of a batch failed (hydra.sweeper.max_failure_rate: "
                f"{settings.max_failure_rate}): " + "; ".join(reasons) + f". The summary: {sweep_dir / 'summary.md'}"
            )
    log.info("study %r: %s", study.study_name, progress(study, settings.n_trials))


def drew(study: Any, trial: Any, space: SearchSpace, extend: Callable[[Any], Any]) -> bool:
    """Draw the parameters of ``trial`` (`SearchSpace` and the custom search space ``extend``);
    False when a re-queued trial's values are refused by them, the trial told failed with why."""
    from optuna.trial import TrialState

    try:
        for name, distribution in space.distributions.items():
            suggest(trial, name, distribution)
        extend(trial)
        misfit = space.misfit(trial.params)  # an enqueued number out of its range: Optuna only warns
    except (ValueError, TypeError) as error:  # Optuna's refusal of an enqueued choice it does not hold
        misfit = str(error)
    if misfit is not None:
        trial.set_user_attr(FAILURE, f"{NOT_RUN}: its parameters do not fit the search space ({misfit})")
        study.tell(trial, state=TrialState.FAIL)
        log.warning("trial %d is not run: %s", trial.number, trial.user_attrs[FAILURE])
        return False
    return True


def launch_trials(study: Any, trials: list[Any], space: SearchSpace, launch: Callable[..., Any]) -> int:
    """Launch the jobs of ``trials`` (each numbered as its trial; consecutive numbers in one call),
    tell each its objective or why it failed; returns how many failed."""
    from optuna.trial import TrialState

    failures = 0
    for group in consecutive(trials):
        overrides = [[*trial_overrides(trial.params), *space.fixed.values()] for trial in group]
        for trial, returned in zip(group, launch(overrides, initial_job_idx=group[0].number)):
            try:
                value = float(returned.return_value)  # the job's exception is raised here
                if not math.isfinite(value):
                    raise ValueError(f"train.py returned {value}, not a finite objective")
            except Exception as error:  # the trial's failure, recorded: the study goes on
                trial.set_user_attr(FAILURE, failure_reason(error))
                study.tell(trial, state=TrialState.FAIL)
                log.warning("trial %d failed: %s", trial.number, trial.user_attrs[FAILURE])
                failures += 1
            else:
                study.tell(trial, value)
    return failures


def consecutive(trials: list[Any]) -> list[list[Any]]:
    """``trials`` in runs of consecutive numbers (one launch each, its jobs numbered as the trials)."""
    groups: list[list[Any]] = []
    for trial in sorted(trials, key=lambda t: t.number):
        if groups and groups[-1][-1].number + 1 == trial.number:
            groups[-1].append(trial)
        else:
            groups.append([trial])
    return groups


def failure_reason(error: BaseException) -> str:
    """A failed job's error in one line: its type and message, a user's mistake (`Mistake`) its
    message only, which names the key or file (at most 500 characters)."""
    text = " ".join((str(error) if isinstance(error, Mistake) else f"{type(error).__name__}: {error}").split())
    return text if len(text) <= 500 else text[:499] + "…"


def completed(study: Any) -> int:
    """How many trials of ``study`` completed."""
    from optuna.trial import TrialState

    return len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)))


def waiting(study: Any) -> int:
    """How many trials of ``study`` wait to be run (failed ones enqueued again: they run even past ``n_trials``)."""
    from optuna.trial import TrialState

    return len(study.get_trials(deepcopy=False, states=(TrialState.WAITING,)))


def progress(study: Any, n_trials: int) -> str:
    """How far ``study`` is, in words: its completed trials of ``n_trials``, how many are still to
    complete, and the trials it holds in other states (failed, waiting to run again, ...)."""
    words = {"FAIL": "failed", "WAITING": "waiting to run"}  # Optuna's TrialState names otherwise, in lower case
    done = completed(study)
    others: dict[str, int] = {}
    for trial in study.get_trials(deepcopy=False):
        if trial.state.name != "COMPLETE":
            state = words.get(trial.state.name, trial.state.name.lower())
            others[state] = others.get(state, 0) + 1
    left = max(0, n_trials - done)
    text = f"{done} of {n_trials} trials (n_trials) complete, {left or 'none'} to go"
    return text + (f"; also {', '.join(f'{count} {state}' for state, count in others.items())}" if others else "")


def reseeded(node: dict[str, Any], offset: int) -> Any:
    """The sampler of its config ``node`` with ``seed + offset`` (the trials a resumed study holds:
    it draws new parameters rather than its first trials' again); unchanged without a seed."""
    if node.get("seed") is not None:
        node = {**node, "seed": int(node["seed"]) + offset}
    return built(OmegaConf.create(node), "hydra.sweeper.sampler")


def check_same_command(study: Any, arguments: list[str], params: Any) -> None:
    """Record the command of a new ``study`` (its user attribute ``command``), or raise `ValueError`
    when it was started by another one: resuming it would mix trials of two settings."""
    command = {
        "overrides": sorted(arguments),
        "params": {str(k): str(v) for k, v in (params or {}).items()},
    }
    recorded = study.user_attrs.get("command")
    if recorded is None:
        study.set_user_attr("command", command)
    elif recorded != command:
        raise ValueError(
            f"the Optuna study {study.study_name!r} was started by another command (overrides "
            f"{recorded['overrides']}, hydra.sweeper.params {recorded['params']}; this one: {command['overrides']}, "
            f"{command['params']}): rerun that command to resume it, or name a new study "
            "(hydra.sweeper.study_name=...) in another sweep folder (hydra.sweep.dir=...)"
        )


def check_same_distributions(study: Any, space: SearchSpace) -> None:
    """Raise `ConfigError` when a parameter of ``space`` was drawn by a trial of ``study`` from
    another kind of distribution (integer, float, log scale) or other choices: Optuna keeps them for
    the whole study, so no trial could draw it."""
    from optuna.distributions import CategoricalDistribution

    for trial in study.get_trials(deepcopy=False):
        for name, held in trial.distributions.items():
            drawn = space.distributions.get(name)
            if drawn is None:
                continue
            same = type(held) is type(drawn) and (
                held.choices == drawn.choices if isinstance(held, CategoricalDistribution) else held.log == drawn.log
            )
            if not same:
                raise ConfigError(
                    f"hydra.sweeper.params.{name}: {drawn} differs from {held}, from which trial {trial.number} of "
                    f"the study {study.study_name!r} drew it; Optuna keeps a parameter's kind and choices for a whole "
                    "study: name a new one (hydra.sweeper.study_name=...) in another sweep folder (hydra.sweep.dir=...)"
                )


def conclude_running_trials(study: Any, sweep_dir: Path) -> None:
    """Tell the trials of ``study`` left running by a killed sweep: complete with the objective of
    their job (the folder of the trial's number, `trial_job`) when it finished, else failed as
    interrupted (`INTERRUPTED`); each noted in the study (`trial_note`)."""
    from optuna.trial import TrialState

    jobs = job_folders(sweep_dir)
    for frozen in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        job = trial_job(frozen, jobs)
        if job is not None and finished_job(job):
            try:
                value = run_objective(job)
            except (OSError, ValueError) as error:
                log.warning("trial %d (%s) finished without an objective: %s", frozen.number, job.name, error)
            else:
                study.set_user_attr(note_key(frozen.number), {"recovered": f"read from {job.name}"})
                study.tell(frozen.number, value)
                continue
        study.set_user_attr(note_key(frozen.number), {"interrupted": True})
        study.tell(frozen.number, state=TrialState.FAIL)


def retry_failed_trials(study: Any, space: SearchSpace, max_retries: int) -> None:
    """Enqueue once more the parameters of each failed trial of ``study`` not yet run again: always
    an interrupted one, one that failed in its job up to ``max_retries`` times in its line of
    retries; not one whose parameters the search space no longer holds (noted in the study)."""
    from optuna.trial import TrialState

    trials, notes = study.get_trials(deepcopy=False), study.user_attrs
    retried = {trial.user_attrs.get(RETRY_OF) for trial in trials}
    by_number = {trial.number: trial for trial in trials}
    for trial in trials:
        if (
            trial.state != TrialState.FAIL
            or trial.number in retried
            or str(trial.user_attrs.get(FAILURE)).startswith(NOT_RUN)
        ):
            continue
        errors, line = 0, trial
        while line is not None:  # the failures by error of this trial and of those it retried
            errors += 0 if interrupted(notes, line) else 1
            line = by_number.get(line.user_attrs.get(RETRY_OF))
        if errors > max_retries:
            continue
        misfit = space.misfit(trial.params)
        if misfit is not None:
            study.set_user_attr(note_key(trial.number), trial_note(notes, trial.number) | {"not_retried": misfit})
            log.warning("trial %d is not run again: %s", trial.number, misfit)
            continue
        study.enqueue_trial(dict(trial.params), user_attrs={RETRY_OF: trial.number})


def keep_best_checkpoints(study: Any, sweep_dir: Path, keep: int | None) -> None:
    """Delete the `CHECKPOINTS_FOLDER` of every finished trial's job but those of the ``keep`` best
    completed trials (None: keep all)."""
    from optuna.study import StudyDirection
    from optuna.trial import TrialState

    if keep is None:
        return
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    maximize = study.direction == StudyDirection.MAXIMIZE
    best = {t.number for t in sorted(complete, key=lambda t: (-t.value if maximize else t.value, t.number))[:keep]}
    jobs = job_folders(sweep_dir)
    for trial in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE, TrialState.FAIL)):
        job = trial_job(trial, jobs)
        if trial.number not in best and job is not None and (job / CHECKPOINTS_FOLDER).is_dir():
            shutil.rmtree(job / CHECKPOINTS_FOLDER)
            log.info("trial %d is not among the %d best: its checkpoints deleted (%s)", trial.number, keep, job.name)
