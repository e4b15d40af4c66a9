"""Sweeps of train.py (`locretrieval.training.sweeps`): the Optuna study of ``hparams_search=localization``
(parallel, resumed after a kill), its search space, its failed trials, the checkpoints it keeps, and
the summary it writes."""

import math
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import helpers
import pandas as pd
import pytest
from omegaconf import OmegaConf
from training_runs import METRIC, SCENE, SMALL_DENSEVLAD

from locretrieval.config import ConfigError
from locretrieval.report.training_summary import write_summary

ROOT = helpers.CONFIGS.parent


def test_the_search_space_names_keys_of_the_training_config():
    """Every swept key exists in train.py's config (a renamed key would fail each trial), each
    loss's parameters in that loss's node; the study resumes from a fixed folder."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(helpers.CONFIGS), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["hparams_search=localization"], return_hydra_config=True)
    sweeper = cfg.hydra.sweeper
    assert sweeper._target_ == "hydra_plugins.locretrieval_sweeper.resumable_optuna.ResumableOptunaSweeper"
    assert sweeper.sampler.seed == 0 and "now" not in OmegaConf.to_container(cfg.hydra.sweep)["dir"]
    for key in sweeper.params:
        assert key == "loss" or OmegaConf.select(cfg, key, default="missing") != "missing", key
    losses = re.fullmatch(r"choice\((.*)\)", sweeper.params.loss).group(1).split(", ")
    assert (
        sorted(losses) == sorted(cfg.loss_search_space) == sorted(p.stem for p in (helpers.CONFIGS / "loss").glob("*"))
    )
    for loss, ranges in cfg.loss_search_space.items():
        node = helpers.compose_config("train", "hparams_search=localization", f"loss={loss}")
        for key in ranges:
            assert OmegaConf.select(node, key, default="missing") != "missing", (loss, key)


def test_a_study_s_progress_says_what_completed_and_what_is_left_in_words():
    import optuna

    from locretrieval.training.sweeps import progress

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study()
    assert progress(study, 2) == "0 of 2 trials (n_trials) complete, 2 to go"
    for value in (1.0, 2.0):
        study.tell(study.ask(), value)
    assert progress(study, 2) == "2 of 2 trials (n_trials) complete, none to go"
    study.tell(study.ask(), state=optuna.trial.TrialState.FAIL)
    study.enqueue_trial({})
    assert progress(study, 5) == "2 of 5 trials (n_trials) complete, 3 to go; also 1 failed, 1 waiting to run"


def test_a_study_started_by_another_command_is_refused_and_a_resumed_sampler_draws_anew(tmp_path):
    import optuna

    from locretrieval.training.sweeps import check_same_command, reseeded

    study = optuna.create_study(study_name="s", storage=f"sqlite:///{tmp_path / 'optuna.db'}", direction="maximize")
    check_same_command(study, ["debug=quick", "seed=1"], {"module.optimizer.lr": "interval(0.1, 0.2)"})
    check_same_command(
        study, ["seed=1", "debug=quick"], {"module.optimizer.lr": "interval(0.1, 0.2)"}
    )  # the same command
    with pytest.raises(ValueError, match=r"study 's' was started by another command .*'seed=2'.*study_name="):
        check_same_command(study, ["debug=quick", "seed=2"], {"module.optimizer.lr": "interval(0.1, 0.2)"})
    with pytest.raises(ValueError, match=r"started by another command .*interval\(0.1, 0.3\)"):
        check_same_command(study, ["debug=quick", "seed=1"], {"module.optimizer.lr": "interval(0.1, 0.3)"})
    node = {"_target_": "optuna.samplers.TPESampler", "seed": 0}
    first = optuna.samplers.TPESampler(seed=0)
    resumed = reseeded(node, 2)  # two trials in the study: seed 2
    draws = [
        optuna.create_study(sampler=sampler).ask().suggest_float("x", 0, 1)
        for sampler in (first, resumed, optuna.samplers.TPESampler(seed=2))
    ]
    assert draws[1] == draws[2] != draws[0]


#: The documented study, three trials in parallel through the joblib launcher with its default workers,
#: each a quick run cut to one epoch of two batches of small images, validated by paradigm 1 alone, on
#: the training tests' tiny scene (30 images of 96x72 px, rendered by the renderer's default workers:
#: debug=quick's 96 of 240x180 px would only make each trial render, describe and validate longer).
SWEEP = [
    "-m",
    "hparams_search=localization",
    "debug=quick",
    "hydra/launcher=joblib_local",
    "hydra.sweeper.n_trials=3",
    "trainer.max_epochs=1",
    "sampler.batches_per_epoch=2",
    "datamodule.image_size=[96,72]",
    "model.max_side=64",  # validation images shrunk: describing them is most of a trial
    *(f"data.render.{key}={value}" for key, value in SCENE.items() if key not in ("conditions", "workers")),
    *(f"data.render.conditions.{key}={value}" for key, value in SCENE["conditions"].items()),
    "paradigms.local_sfm.enabled=false",
    "paradigms.global_sfm.enabled=false",
    *SMALL_DENSEVLAD,  # each trial's reference (the study is of the trained descriptor's metric)
]


def sweep(root: Path, log: Path) -> subprocess.Popen:
    """The sweep in its own session (killed with its workers), its output into ``log`` (a pipe
    nobody reads while the test waits would fill and stop it)."""
    command = [sys.executable, str(ROOT / "train.py"), *SWEEP, f"paths.root_dir={root}"]
    with log.open("w") as output:
        return subprocess.Popen(command, cwd=root, stdout=output, stderr=subprocess.STDOUT, start_new_session=True)


def trials(database: Path) -> list[tuple[int, str, float | None]]:
    """``(number, state, value)`` of every trial of the SQLite study, read with sqlite3 alone."""
    with sqlite3.connect(database) as connection:
        return connection.execute(
            "SELECT t.number, t.state, v.value FROM trials t LEFT JOIN trial_values v ON v.trial_id = t.trial_id "
            "ORDER BY t.number"
        ).fetchall()


def logged_interval(job: Path) -> tuple[datetime, datetime]:
    """When a job's train.log started and ended."""
    stamps = re.findall(r"^\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d+)\]", (job / "train.log").read_text(), re.MULTILINE)
    return tuple(datetime.strptime(stamp, "%Y-%m-%d %H:%M:%S,%f") for stamp in (stamps[0], stamps[-1]))


@pytest.mark.slow
def test_an_optuna_sweep_killed_after_its_first_trial_resumes_without_running_it_again(tmp_path):
    folder = tmp_path / "multirun" / "train" / "localization"  # hparams_search's fixed sweep folder
    killed, deadline = sweep(tmp_path, tmp_path / "killed.log"), time.monotonic() + 900
    while not list(folder.glob("*/summary.json")):
        assert killed.poll() is None and time.monotonic() < deadline, (tmp_path / "killed.log").read_text()[-3000:]
        time.sleep(0.2)
    os.killpg(killed.pid, signal.SIGKILL)  # the sweep and its joblib workers
    killed.wait()
    log = (tmp_path / "killed.log").read_text()
    assert "Joblib.Parallel(n_jobs=2" in log and "is launching 2 jobs" in log
    started = trials(folder / "optuna.db")
    finished = {path: path.stat().st_mtime_ns for path in folder.glob("*/summary.json")}
    # the first batch: a trial finished, maybe both, and then the next batch's trial may have begun
    assert len(started) >= 2 and len(finished) >= 1
    jobs = {int(path.name.split("_")[0]): path for path in folder.iterdir() if path.is_dir()}
    (first_start, first_end), (second_start, second_end) = logged_interval(jobs[0]), logged_interval(jobs[1])
    assert first_start < second_end and second_start < first_end  # the two trials of the batch ran at once

    resumed = sweep(tmp_path, tmp_path / "resumed.log")
    assert resumed.wait(timeout=900) == 0, (tmp_path / "resumed.log").read_text()[-3000:]
    study = trials(folder / "optuna.db")
    interrupted = len(started) - len(finished)
    assert [state for _, state, _ in study].count("COMPLETE") == 3
    assert len(study) == 3 + interrupted  # an interrupted trial ran once more, a finished one not again
    assert {path: path.stat().st_mtime_ns for path in finished} == finished
    jobs = {int(path.name.split("_")[0]): path for path in folder.iterdir() if path.is_dir()}
    for number, state, value in study:
        if state == "COMPLETE":  # the value main returned (or, for a job finished before the kill, read back)
            history = pd.read_csv(jobs[number] / "validation.csv")
            expected = history[(history["metric"] == METRIC) & (history["epoch"] >= 0)]["value"].max()
            assert math.isfinite(value) and value == expected, number

    import optuna

    loaded = optuna.load_study(study_name="localization", storage=f"sqlite:///{folder / 'optuna.db'}")
    search = helpers.compose_config("train", "hparams_search=localization").loss_search_space
    for trial in loaded.trials:  # each trial drew its own loss's parameters and no other loss's
        drawn = {key for key in trial.params if key.startswith("module.loss.")}
        assert drawn == set(search[trial.params["loss"]]), trial.params

    top = max(value for _, state, value in study if state == "COMPLETE")
    best = min(number for number, state, value in study if state == "COMPLETE" and value == top)  # the first of equals
    summary = pd.read_csv(folder / "summary.csv")
    assert summary["trial"].astype(int).tolist() == [number for number, _, _ in study]
    assert summary.loc[summary["best"], "trial"].astype(int).tolist() == [best]
    markdown = (folder / "summary.md").read_text()
    assert f"| {best} (best)" in markdown and "## Optuna study `localization`" in markdown
    assert not re.search(r"\bnan\b|\binf\b", markdown, re.IGNORECASE)
    figures = (folder / "optuna.html").read_text()
    assert "Optimization History Plot" in figures and "plotly" in figures

    regenerated = subprocess.run(
        [sys.executable, str(ROOT / "report.py"), str(folder), "--output", str(tmp_path / "report")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert regenerated.returncode == 0, regenerated.stderr[-3000:]
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "report" / "summary.csv"), summary)


def positions(distribution, count: int) -> list:
    """``count`` values of an Optuna ``distribution`` spanning it: its bounds and, between them, a point
    that is no round number (a float range's middle would show a float drawn where an integer is
    needed); a categorical's choices in turn."""
    from optuna.distributions import CategoricalDistribution, IntDistribution

    if isinstance(distribution, CategoricalDistribution):
        return [distribution.choices[index % len(distribution.choices)] for index in range(count)]
    low, high, inner = distribution.low, distribution.high, math.sqrt(2) - 1
    middle = low * (high / low) ** inner if distribution.log else low + (high - low) * inner
    values = [low, round(middle) if isinstance(distribution, IntDistribution) else middle, high]
    return [values[index % 3] for index in range(count)]


def check_drawn_objects(cfg, keys) -> None:
    """The objects a trial's drawn ``keys`` configure, checked as train.py checks them before any
    work (`check_node`: keys and types) and built as it builds them (a range check of theirs too)."""
    from training_runs import random_pairs

    from locretrieval.config import built, check_node

    nodes = {"module.loss" if key == "loss" else key.rsplit(".", 1)[0] for key in keys}
    for key in sorted(nodes):
        while "_target_" not in OmegaConf.select(cfg, key):  # the object node a key belongs to
            key = key.rsplit(".", 1)[0]
        check_node(OmegaConf.select(cfg, key), key)
    pairs = random_pairs(64, seed=0)
    loss = built(cfg.module.loss, "module.loss")
    if cfg.module.get("memory"):
        built(cfg.module.memory, "module.memory", loss=loss, pairs=pairs)
    built(cfg.sampler, "sampler", pairs=pairs)
    built(cfg.augmentation, "augmentation")


@pytest.mark.smoke
@pytest.mark.parametrize("search", sorted(path.stem for path in (helpers.CONFIGS / "hparams_search").glob("*.yaml")))
def test_every_range_of_a_search_space_draws_values_its_training_config_accepts(search, tmp_path):
    """The bounds and an inner value of every range, each choice, for every loss the study draws (its
    own parameters too), drawn as the sweeper draws them (Optuna's trial, the custom search space):
    the training config with the drawn values passes train.py's checks of what they configure and
    builds those objects. Composed once per loss, the values set as Hydra sets a value override."""
    import optuna
    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.utils import get_object

    from locretrieval.report.training_runs import trial_overrides
    from locretrieval.training.sweeps import SearchSpace, suggest

    fixed = [f"hparams_search={search}", f"paths.root_dir={tmp_path}", f"output_dir={tmp_path}/run"]
    with initialize_config_dir(config_dir=str(helpers.CONFIGS), version_base="1.3"):
        sweep = compose(config_name="train", overrides=fixed, return_hydra_config=True)
        space = SearchSpace.parse([f"{key}={value}" for key, value in sweep.hydra.sweeper.params.items()])
        custom = sweep.hydra.sweeper.custom_search_space
        losses = space.distributions["loss"].choices if "loss" in space.distributions else [None]
        study, checked = optuna.create_study(), 0
        for loss in losses:
            loss_choice = [f"loss={loss}"] if loss and loss != sweep.hydra.runtime.choices.loss else []
            composed = compose(config_name="train", overrides=[*fixed, *loss_choice]) if loss_choice else sweep
            ranges = (sweep.get("loss_search_space") or {}).get(loss) or {}
            own = SearchSpace.parse([f"{key}={value}" for key, value in ranges.items()]).distributions
            distributions = {name: d for name, d in space.distributions.items() if name != "loss"} | own
            count = max([3, *(len(d.choices) for d in distributions.values() if hasattr(d, "choices"))])
            for index in range(count):
                params = {name: positions(d, count)[index] for name, d in distributions.items()}
                study.enqueue_trial(params | ({"loss": loss} if loss else {}))
                trial = study.ask()
                for name, distribution in space.distributions.items():
                    suggest(trial, name, distribution)
                if custom:
                    get_object(custom)(sweep, trial)
                assert trial.params == params | ({"loss": loss} if loss else {})
                cfg = composed.copy()
                overrides = [item for item in trial_overrides(trial.params) if not item.startswith("loss=")]
                for override in OverridesParser.create().parse_overrides(overrides):
                    OmegaConf.update(cfg, override.key_or_group, override.value(), merge=True)
                check_drawn_objects(cfg, trial.params)
                checked += 1
    assert checked >= 3 * len(losses)


#: A task of the project's sweeper, as cheap as a task gets: it returns its ``x`` and fails on purpose
#: as job 1 while the file ``fail_marker`` exists. Its jobs are named ``train`` (the summary's sweeps;
#: summarized once by the test, not by the callback at the end of each run).
SWEEP_APP = """
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg):
    if HydraConfig.get().job.num == 1 and Path(cfg.fail_marker).exists():
        raise ValueError("failing on purpose")
    return cfg.x


if __name__ == "__main__":
    main()
"""


SWEEP_APP_CONFIG = """
defaults:
  - override hydra/sweeper: optuna
  - override hydra/launcher: joblib_local
  - _self_
x: 0.5
y: a
fail_marker: {marker}
hydra:
  searchpath: [file://{configs}]
  job: {{name: train}}
  sweep: {{dir: {sweep}, subdir: "${{hydra.job.num}}"}}
  sweeper:
    study_name: app
    n_trials: 3
    max_failure_rate: 0.5
    sampler: {{seed: 0}}
    params: {{x: "interval(0, 1)", y: "choice(a, b)"}}
"""


@pytest.mark.smoke
def test_a_failed_trial_records_why_and_the_rerun_of_the_sweep_runs_it_again(tmp_path):
    """The project's sweeper through Hydra with the joblib launcher (2 jobs at once): job 1 fails on
    purpose, its reason is stored in the study and shown in the summary's state, another trial takes
    its place; rerunning the command runs its parameters again as a new trial."""
    import optuna

    marker, sweep = tmp_path / "fail", tmp_path / "sweep"
    (tmp_path / "conf").mkdir()
    (tmp_path / "conf" / "config.yaml").write_text(
        SWEEP_APP_CONFIG.format(marker=marker, configs=helpers.CONFIGS, sweep=sweep)
    )
    (tmp_path / "app.py").write_text(SWEEP_APP)
    marker.touch()
    done = subprocess.run([sys.executable, "app.py", "-m"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "is launching 2 jobs" in done.stdout, done.stderr[-3000:]
    assert [state for _, state, _ in trials(sweep / "optuna.db")] == ["COMPLETE", "FAIL", "COMPLETE", "COMPLETE"]
    marker.unlink()
    done = subprocess.run([sys.executable, "app.py", "-m"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "is launching 1 jobs" in done.stdout, done.stderr[-3000:]
    study = optuna.load_study(study_name="app", storage=f"sqlite:///{sweep / 'optuna.db'}")
    failed, retry = study.trials[1], study.trials[4]
    assert failed.user_attrs["failure"] == "ValueError: failing on purpose"
    assert retry.state.name == "COMPLETE" and retry.params == failed.params and retry.user_attrs["retry_of"] == 1
    assert retry.value == failed.params["x"]  # what the task returned
    rows = pd.read_csv(write_summary([sweep], sweep).with_suffix(".csv")).set_index("trial")
    assert rows.loc[1, "state"] == "fail: ValueError: failing on purpose"
    assert rows.loc[1, "note"].startswith("run again as trial 4") and rows.loc[4, "state"] == "complete"


def sweep_config(folder: Path, *command_line: str, **sweeper) -> OmegaConf:
    """A multirun's config as the project's sweeper gets it: configs/hydra/sweeper/optuna.yaml with the
    random sampler, ``sweeper`` keys replacing its own, the Hydra overrides of ``command_line``."""
    node = OmegaConf.load(helpers.CONFIGS / "hydra" / "sweeper" / "optuna.yaml")
    node.pop("defaults")
    node.sampler = OmegaConf.load(helpers.CONFIGS / "hydra" / "sweeper" / "sampler" / "random.yaml")
    node.sampler.seed, node.params = 0, sweeper.pop("params", {"x": "interval(0, 1)"})
    hydra = {"sweep": {"dir": str(folder)}, "job": {"name": "train"}, "runtime": {"choices": {}}}
    hydra |= {"overrides": {"hydra": list(command_line), "task": []}}
    return OmegaConf.create({"hydra": {**hydra, "sweeper": OmegaConf.merge(node, sweeper)}})


class Jobs:
    """Hydra's launcher, in this process: each job's folder as Hydra writes it (its number, overrides
    and a checkpoint) and its `JobReturn`, the value of ``objective(params)`` or the error it raises."""

    def __init__(self, folder: Path, objective):
        self.folder, self.objective, self.launched = folder, objective, []

    def launch(self, overrides, initial_job_idx):
        from hydra.core.utils import JobReturn, JobStatus

        returns = []
        for number, items in enumerate(overrides, start=initial_job_idx):
            job = self.folder / str(number)
            (job / ".hydra").mkdir(parents=True)
            OmegaConf.save(OmegaConf.create({"hydra": {"job": {"num": number}}}), job / ".hydra" / "hydra.yaml")
            OmegaConf.save(OmegaConf.create(list(items)), job / ".hydra" / "overrides.yaml")
            (job / "checkpoints").mkdir()
            (job / "checkpoints" / "last.ckpt").write_bytes(b"weights")
            self.launched.append(number)
            try:
                value = self.objective(dict(item.split("=", 1) for item in items))
                returns.append(JobReturn(overrides=list(items), status=JobStatus.COMPLETED, _return_value=value))
            except Exception as error:
                returns.append(JobReturn(overrides=list(items), status=JobStatus.FAILED, _return_value=error))
        return returns


def test_failures_beyond_the_failure_rate_stop_the_study_with_their_reasons_and_a_summary(tmp_path):
    from locretrieval.training.sweeps import SweepStopped, optimize

    def diverging(params):
        raise FloatingPointError("the loss diverged")

    with pytest.raises(SweepStopped, match=r"2 of the 2 trials .* trial 0: FloatingPointError: the loss diverged"):
        optimize(sweep_config(tmp_path, max_failure_rate=0.5), [], Jobs(tmp_path, diverging).launch)
    table = pd.read_csv(tmp_path / "summary.csv")
    assert table["state"].tolist() == ["fail: FloatingPointError: the loss diverged"] * 2


def test_only_the_best_trials_keep_their_checkpoints(tmp_path):
    from locretrieval.training.sweeps import optimize

    jobs = Jobs(tmp_path, lambda params: float(params["x"]))
    optimize(sweep_config(tmp_path, n_trials=4, keep_checkpoints=1), [], jobs.launch)
    values = {number: value for number, _, value in trials(tmp_path / "optuna.db")}
    best = max(values, key=values.get)
    assert jobs.launched == [0, 1, 2, 3]
    assert [number for number in values if (tmp_path / str(number) / "checkpoints").exists()] == [best]


def test_a_running_trial_outside_the_search_space_is_concluded_with_its_reason_not_run_again(tmp_path):
    """A study whose trial was left running with a value the search space no longer holds: the rerun
    tells it failed and does not enqueue it (it would fail every rerun), says why in the summary, and
    runs the study; a trial left enqueued with such a value is told failed without being launched."""
    import optuna

    from locretrieval.training.sweeps import optimize, write_sweep_summary

    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    left = optuna.create_study(study_name="sweep", storage=storage, direction="maximize")
    left.set_user_attr("command", {"overrides": [], "params": {"x": "interval(0, 1)"}})
    left.enqueue_trial({"x": 7.5})
    left.ask().suggest_float("x", 0, 10)  # running when its sweep was killed: x=7.5
    left.enqueue_trial({"x": 9.0})  # waiting, the same
    jobs = Jobs(tmp_path, lambda params: float(params["x"]))
    for _ in range(2):  # the second rerun has nothing left to do
        optimize(sweep_config(tmp_path, n_trials=2, max_failure_rate=0.5), [], jobs.launch)
    study = optuna.load_study(study_name="sweep", storage=storage)
    assert [trial.state.name for trial in study.trials] == ["FAIL", "FAIL", "COMPLETE", "COMPLETE"]
    assert jobs.launched == [2, 3]
    assert study.trials[1].user_attrs["failure"] == (
        "not run: its parameters do not fit the search space (x=9.0 is outside [0.0, 1.0])"
    )
    rows = pd.read_csv(write_sweep_summary(sweep_config(tmp_path)).with_suffix(".csv")).set_index("trial")
    assert rows.loc[0, "state"] == "fail: interrupted: the sweep stopped while it ran"
    assert rows.loc[0, "note"] == "not run again: x=7.5 is outside [0.0, 1.0]"


def test_a_study_whose_trials_drew_a_parameter_from_other_choices_is_refused_by_name(tmp_path):
    """Optuna keeps a categorical parameter's choices for a whole study: a rerun whose ``loss`` has
    other choices than a trial left running drew it from is refused naming the parameter and what to do."""
    import optuna

    from locretrieval.training.sweeps import optimize

    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    left = optuna.create_study(study_name="sweep", storage=storage, direction="maximize")
    left.set_user_attr("command", {"overrides": [], "params": {"loss": "choice(ap, listwise)"}})
    left.ask().suggest_categorical("loss", ["removed", "ap"])
    config = sweep_config(tmp_path, params={"loss": "choice(ap, listwise)"})
    for _ in range(2):  # the same named error each time, the running trial told failed once
        with pytest.raises(ConfigError, match=r"hydra.sweeper.params.loss: .* trial 0 of the study 'sweep' .*"):
            optimize(config, [], Jobs(tmp_path, lambda params: 1.0).launch)
    assert [trial.state.name for trial in optuna.load_study(study_name="sweep", storage=storage).trials] == ["FAIL"]


def test_the_study_stays_in_the_sweep_folder_unless_the_command_line_names_another_storage(tmp_path):
    from locretrieval.training.sweeps import study_storage

    elsewhere = f"sqlite:///{tmp_path / 'elsewhere' / 'x.db'}"
    assert study_storage(sweep_config(tmp_path / "sweep")) == f"sqlite:///{tmp_path / 'sweep' / 'optuna.db'}"
    assert study_storage(sweep_config(tmp_path / "sweep", storage=f"sqlite:///{tmp_path}/sweep/a.db")).endswith("a.db")
    with pytest.raises(ConfigError, match=r"hydra.sweeper.storage: .*x.db' is not a file in the sweep folder"):
        study_storage(sweep_config(tmp_path / "sweep", storage=elsewhere))  # a multirun.yaml's, say
    named = sweep_config(tmp_path / "sweep", f"hydra.sweeper.storage={elsewhere}", storage=elsewhere)
    assert study_storage(named) == elsewhere
    assert type(study_storage(sweep_config(tmp_path / "sweep", storage="journal"))).__name__ == "JournalStorage"
    assert not (tmp_path / "elsewhere").exists()
