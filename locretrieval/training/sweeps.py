"""Sweeps of train.py (``-m``): the summary written at the end of every multirun, the loss
parameters of ``hparams_search=localization`` and the resuming of its Optuna study.

Imported by every train.py run (the Hydra callback): the heavy modules only where they are used.
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger(__name__)

#: A finished train.py run: the file it writes last (rank 0, after its report).
FINISHED_FILE = "summary.json"


class SweepSummary(Callback):
    """``hydra.callbacks.sweep_summary``: at the end of a multirun (a grid or an Optuna study),
    `write_summary` of its jobs into the sweep folder."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        from locretrieval.training.summary import write_summary

        folder = Path(config.hydra.sweep.dir)
        log.info("summary of the sweep: %s", write_summary([folder], folder))


def loss_parameters(cfg: DictConfig, trial: Any) -> None:
    """``hydra.sweeper.custom_search_space`` of ``hparams_search=localization``: the parameters of
    the loss a trial drew (or the ``loss`` fixed on the command line), each suggested from its range
    in ``loss_search_space.<loss>`` (``{key: range}``, ranges in the sweeper's grammar: ``interval``,
    ``tag(log, ...)``, ``choice``), as the sweeper suggests ``hydra.sweeper.params``."""
    from hydra_plugins.hydra_optuna_sweeper._impl import create_params_from_overrides

    loss = trial.params.get("loss", trial.user_attrs.get("loss", cfg.hydra.runtime.choices.get("loss")))
    ranges = (cfg.get("loss_search_space") or {}).get(loss) or {}
    distributions, _ = create_params_from_overrides([f"{key}={value}" for key, value in ranges.items()])
    for name, distribution in distributions.items():
        trial._suggest(name, distribution)  # what the sweeper does with hydra.sweeper.params


def finished_job(folder: Path) -> bool:
    """Whether the train.py job in ``folder`` finished: its `FINISHED_FILE` written whole."""
    try:
        json.loads((folder / FINISHED_FILE).read_text())
    except (OSError, ValueError):
        return False
    return True


def job_folders(sweep_dir: Path) -> dict[int, Path]:
    """The job folders of a multirun by job number (``hydra.job.num`` of ``.hydra/hydra.yaml``)."""
    jobs = {}
    for path in sorted(sweep_dir.glob("*/.hydra/hydra.yaml")):
        jobs[int(OmegaConf.load(path).hydra.job.num)] = path.parent.parent
    return jobs


def job_overrides(folder: Path) -> list[str]:
    """A job's command-line overrides (``.hydra/overrides.yaml``)."""
    path = folder / ".hydra" / "overrides.yaml"
    return [str(item) for item in OmegaConf.load(path)] if path.is_file() else []


def trial_overrides(params: dict[str, Any]) -> list[str]:
    """A trial's parameters as the Optuna sweeper passes them to its job (``key=value``)."""
    return [f"{name}={value}" for name, value in params.items()]


def resume_study(sweeper: Any, arguments: list[str]) -> None:
    """Prepare the Optuna sweeper's implementation (``OptunaSweeperImpl``, after its ``setup``)
    to go on with the study it stores, before its ``sweep(arguments)``:

    - the sweep folder is made (a SQLite storage inside it is then created there) and the sweep's
      config saved there as the basic sweeper saves it (``multirun.yaml``: its summary reads it);
    - a study started by another command (other ``arguments`` or ``hydra.sweeper.params``) is refused;
    - the trials a killed sweep left running are told: finished when their job wrote its results
      (the objective from its ``validation.csv``), else failed and enqueued again with their parameters;
    - ``n_trials`` counts the finished trials (a rerun runs the rest; a larger ``n_trials`` extends it);
    - the sampler's ``seed`` is offset by the trials the study holds, so a resumed study draws new
      parameters rather than its first trials' again;
    - job numbers go on from the study's trial numbers (a job's number is its trial's).
    """
    Path(sweeper.sweep_dir).mkdir(parents=True, exist_ok=True)
    OmegaConf.save(sweeper.config, Path(sweeper.sweep_dir) / "multirun.yaml")
    if sweeper.storage is None:
        return
    import optuna

    study = optuna.create_study(
        study_name=sweeper.study_name,
        storage=sweeper.storage,
        directions=sweeper._get_directions(),
        load_if_exists=True,
    )
    check_same_command(study, arguments, sweeper.params)
    interrupted = conclude_running_trials(study, Path(sweeper.sweep_dir))
    trials = study.get_trials(deepcopy=False)
    finished = [t for t in trials if t.state.is_finished() and not t.user_attrs.get("interrupted")]
    waiting = [t.number for t in trials if t.state == optuna.trial.TrialState.WAITING]
    if trials:
        log.info(
            "study %r: %d trial(s) finished, %d interrupted and run again; %d of n_trials=%d to go",
            study.study_name, len(finished), interrupted, max(0, sweeper.n_trials - len(finished)), sweeper.n_trials,
        )  # fmt: skip
        sweeper.sampler = reseeded(sweeper.sampler, sweeper.config.hydra.sweeper.get("sampler"), len(trials))
    sweeper.n_trials = max(0, sweeper.n_trials - len(finished))
    sweeper.job_idx = min(waiting, default=len(trials))


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


def conclude_running_trials(study: Any, sweep_dir: Path) -> int:
    """Tell the trials of ``study`` left running by a killed sweep: complete with the objective of
    their job (the folder of the trial's number) when it finished, else failed (user attribute
    ``interrupted``) and enqueued again with their parameters. Returns how many were enqueued."""
    import optuna
    from optuna.trial import TrialState

    from locretrieval.training.objective import run_objective

    jobs = job_folders(sweep_dir)
    interrupted = 0
    with warnings.catch_warnings():  # Optuna 2.10 calls enqueueing experimental
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        for frozen in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            job = jobs.get(frozen.number)
            same = job is not None and set(trial_overrides(frozen.params)) <= set(job_overrides(job))
            if same and finished_job(job):
                try:
                    value = run_objective(job)
                except (OSError, ValueError) as error:
                    log.warning("trial %d (%s) finished without an objective: %s", frozen.number, job.name, error)
                else:  # the storage's user attributes: a trial of another process has no Trial object here
                    study._storage.set_trial_user_attr(frozen._trial_id, "recovered", f"read from {job.name}")
                    study.tell(frozen.number, value)
                    continue
            study._storage.set_trial_user_attr(frozen._trial_id, "interrupted", True)
            study.tell(frozen.number, state=TrialState.FAIL)
            study.enqueue_trial(dict(frozen.params))
            interrupted += 1
    return interrupted


def reseeded(sampler: Any, node: Any, offset: int) -> Any:
    """``sampler`` built again from its config ``node`` with ``seed + offset`` (unchanged without a seed)."""
    from hydra.utils import instantiate

    if node is None or node.get("seed") is None or node.get("_partial_"):
        return sampler
    return instantiate(OmegaConf.merge(node, {"seed": int(node.seed) + offset}))
