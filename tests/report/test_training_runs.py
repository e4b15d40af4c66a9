"""train.py's run and sweep folders as someone else's: their files read as written, nothing opened or
made outside them, their values safe in a spreadsheet (`locretrieval.report.training_runs` and the summary)."""

import csv
import hashlib
from pathlib import Path

import pandas as pd
import pytest
from omegaconf import OmegaConf
from training_runs import gap_run

from locretrieval.errors import DataFileError
from locretrieval.report.training_summary import write_summary
from locretrieval.training.sweeps import SWEEPER

ROW = [("approximation/ewb/k3/5m_10deg", 10.0, 40.0, 20.0, 60.0)]


def shared_sweep(folder: Path, storage: str, overrides: list[str], **job) -> Path:
    """A sweep folder of the project's sweeper with one finished job (number 0, its ``overrides``),
    its multirun.yaml naming ``storage``; ``job``: keys replacing those of the job's config.yaml."""
    folder.mkdir(parents=True)
    multirun = {"hydra": {"job": {"name": "train"}, "sweeper": {"_target_": SWEEPER, "storage": storage}}}
    OmegaConf.save(OmegaConf.create(multirun), folder / "multirun.yaml")
    run = gap_run(folder, "0", 40.0, ROW)
    OmegaConf.save(OmegaConf.create({"hydra": {"job": {"num": 0}}}), run / ".hydra" / "hydra.yaml")
    OmegaConf.save(OmegaConf.create(overrides), run / ".hydra" / "overrides.yaml")
    config = OmegaConf.merge(OmegaConf.load(run / "config.yaml"), job)
    (run / "config.yaml").write_text(OmegaConf.to_yaml(config))
    return folder


@pytest.mark.smoke
def test_a_shared_sweeps_summary_shows_its_values_as_written_and_opens_nothing_outside_it(tmp_path, monkeypatch):
    """Its overrides and config name environment variables (``${oc.env:...}``) and its multirun.yaml a
    database elsewhere: the summary shows the text as written, no value of the environment, makes no
    database, and says why it read no study; cells a spreadsheet would run as formulas are quoted."""
    monkeypatch.setenv("SWEEP_SECRET", "s3cr3t-value")
    elsewhere = tmp_path / "elsewhere" / "x.db"
    sweep = shared_sweep(
        tmp_path / "sweep",
        f"sqlite:///{elsewhere}",
        ["seed=${oc.env:SWEEP_SECRET}", "debug=quick"],
        optimized_metric="${oc.env:SWEEP_SECRET}",
    )
    formulas = [gap_run(tmp_path, label, -3.0, ROW) for label in ("=2+5", "@SUM(A1)", "+1", "-1", "\tcmd")]
    output = tmp_path / "summary"
    markdown = write_summary([sweep, *formulas], output).read_text()
    assert not elsewhere.parent.exists()
    assert "**study not read**: sweep: its storage" in markdown and "is not a file in the sweep folder" in markdown
    for name in ("summary.md", "summary.html", "summary.csv"):
        assert "s3cr3t" not in (output / name).read_text(), name
    with (output / "summary.csv").open(newline="") as file:
        rows = {row["trial"]: row for row in csv.DictReader(file)}
    assert rows["sweep/0"]["overrides"] == "seed=${oc.env:SWEEP_SECRET} debug=quick"
    assert "optimized_metric: '${oc.env:SWEEP_SECRET}' was not logged" in rows["sweep/0"]["note"]
    assert sorted(rows) == sorted(["sweep/0", "'=2+5", "'@SUM(A1)", "'+1", "'-1", "'\tcmd"])
    assert rows["'=2+5"]["objective"] == "-3.0"  # a number stays one
    raw = (output / "summary.csv").read_text()
    assert '\n"\'=2+5",' in raw and '\n"\'@SUM(A1)",' in raw  # quoted, the quote inside
    assert pd.read_csv(output / "summary.csv")["objective"].tolist()[1:] == [-3.0] * 5


@pytest.mark.smoke
def test_a_sweeps_own_study_is_read_without_changing_it(tmp_path):
    import optuna

    sweep = shared_sweep(tmp_path / "sweep", "sqlite", ["debug=quick"])
    study = optuna.create_study(study_name="mine", storage=f"sqlite:///{sweep / 'optuna.db'}", direction="maximize")
    study.enqueue_trial({"x": 0.5})
    study.tell(study.ask({"x": optuna.distributions.FloatDistribution(0, 1)}), 40.0)
    before = hashlib.sha256((sweep / "optuna.db").read_bytes()).hexdigest()
    markdown = write_summary([sweep], tmp_path / "summary").read_text()
    assert "## Optuna study `mine`" in markdown and "- **trials**: 1 complete" in markdown
    assert hashlib.sha256((sweep / "optuna.db").read_bytes()).hexdigest() == before
    assert sorted(path.name for path in sweep.iterdir()) == ["0", "multirun.yaml", "optuna.db"]


def test_a_job_number_that_is_no_number_is_a_named_error(tmp_path):
    sweep = shared_sweep(tmp_path / "sweep", "sqlite", ["debug=quick"])
    OmegaConf.save(OmegaConf.create({"hydra": {"job": {"num": "abc"}}}), sweep / "0" / ".hydra" / "hydra.yaml")
    with pytest.raises(DataFileError, match=r"0/.hydra/hydra.yaml: hydra.job.num: 'abc' is not a job number"):
        write_summary([sweep], tmp_path / "summary")
