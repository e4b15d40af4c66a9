"""One clear screen per mistake: evaluate.py, train.py and report.py end a mistake of the user's with
its message first (the fix named), at most 15 lines, no traceback and exit status 1, before any
expensive work; ``HYDRA_FULL_ERROR=1`` shows the traceback; a key the config lacks is named with
the nearest ones, also where Hydra itself would refuse the override."""

import os
import re
import runpy
import subprocess
import sys
from pathlib import Path

import pytest
from hydra.errors import InstantiationException
from omegaconf import OmegaConf

from locretrieval import cli
from locretrieval.cli import Mistake, device_problems, group_override_problems, reported_mistakes, unknown_override_keys
from locretrieval.config import ConfigError
from locretrieval.errors import DataFileError
from locretrieval.models.files.weights import WEIGHT_SOURCES

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"


def mistakes(root: Path) -> dict[str, tuple[list[str], str, str | None, str | None]]:
    """Each mistake: its command (a script of the repository's root, or ``-m locretrieval``: the
    installed command; run in ``root``, an empty folder), the start of the first line it must print,
    and words the output must hold and must not."""
    data = root / "data"
    return {
        "an option a config group lacks": (
            ["-m", "locretrieval", "evaluate", "model=netvald"],
            "model=netvald: no such option of model; did you mean netvlad",
            "densevlad, ",  # the options, on the same line
            "Config search path",
        ),
        "a config group the command lacks": (
            ["evaluate.py", "loss=apx"],
            "loss: evaluate has no config group loss; it is train's (locretrieval train loss=apx)",
            "evaluate's groups: baselines, data, ",
            "+loss",
        ),
        "a key of another command": (
            ["train.py", "dry_run=yes"],
            "dry_run: unknown key; expected one of ",
            "instead, debug=quick",
            None,
        ),
        "a device that is none, named as typed": (
            ["-m", "locretrieval", "evaluate", "device=gpu"],
            "device=gpu: no such device; choose auto (a GPU when there is one), cpu, cuda or cuda:N",
            None,
            "sfm.matching",
        ),
        "an export the model cannot do": (
            ["export.py", "export=[onnx]"],
            "export=[onnx]: model 'densevlad' (DenseVLAD) is not a torch network",
            "model=checkpoint model.weights=",
            None,
        ),
        "a published dataset not installed": (
            ["train.py", "data=baidu", "loss=ap"],
            f"kapture folder not found: {data}/baidu-mall/mapping",
            'kapture_download_dataset.py install "baidu*"',
            None,
        ),
        "published weights not downloaded": (
            ["evaluate.py", "model=netvlad"],
            f"model 'netvlad': weight file not found: {data}/weights/Pitts30K_struct.mat; "
            "download it and set model.weights=",
            WEIGHT_SOURCES["netvlad"].publisher,
            None,
        ),
        "a mistyped folder of one's own data": (
            ["evaluate.py", "data=kapture", f"data.mapping={root}/nope", "data.queries=[query]"],
            f"kapture folder not found: {root}/nope (dataset 'kapture', its mapping)",
            None,
            "kapture_download_dataset",
        ),
        "a mistyped key Hydra refuses": (
            ["train.py", "trainer.max_epoch=2"],
            "trainer.max_epoch: unknown key; expected one of ['_target_', ",
            "did you mean max_epochs?",
            "+trainer.max_epoch",
        ),
    }


@pytest.mark.slow
def test_each_mistake_ends_with_its_fix_first_on_one_short_screen(tmp_path):
    """The mistakes run at once (each fails before any expensive work: a few seconds of imports),
    in a folder holding no data or weights, with the default settings otherwise."""
    env = {key: value for key, value in os.environ.items() if not key.startswith(("LOCRETRIEVAL_", "HYDRA_"))}
    cases = mistakes(tmp_path)
    started = {
        name: subprocess.Popen(
            [sys.executable, *command]
            if command[0] == "-m"
            else [sys.executable, str(ROOT / command[0]), *command[1:]],
            cwd=tmp_path,
            env={**env, "PYTHONPATH": str(ROOT)},
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for name, (command, *_) in cases.items()
    }
    for name, process in started.items():
        output, _ = process.communicate(timeout=240)
        _, first, holds, lacks = cases[name]
        lines = output.splitlines()
        assert process.returncode == 1, (name, output)
        assert lines[0].startswith(first), (name, output)
        assert "Traceback" not in output and len(lines) <= 15, (name, output)
        assert holds is None or holds in output, (name, output)
        assert lacks is None or lacks not in output, (name, output)
    assert not (tmp_path / ".cache").exists()  # no scene rendered, no descriptor computed


def test_a_mistake_keeps_its_traceback_with_hydra_full_error_and_a_fault_always(monkeypatch, capsys):
    with pytest.raises(SystemExit) as stopped, reported_mistakes():
        raise DataFileError("/x/table.csv", "damaged", "fix it")
    assert stopped.value.code == 1 and capsys.readouterr().err == "/x/table.csv: damaged; fix it\n"
    with pytest.raises(SystemExit), reported_mistakes():  # Hydra's instantiate wraps the mistake of a target
        raise InstantiationException("Error in call to target 'x'") from FileNotFoundError("/x/weights.pt")
    assert capsys.readouterr().err == "/x/weights.pt\n"
    with pytest.raises(KeyError), reported_mistakes():  # a fault of the program: its traceback
        raise KeyError("x")
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    with pytest.raises(ConfigError, match="a.b: wrong"), reported_mistakes():
        raise ConfigError("a.b: wrong")


def test_a_value_left_to_the_command_line_is_named_with_how_to_give_it(capsys):
    data = OmegaConf.create({"data": {"mapping": "/m", "queries": "???"}}).data
    with pytest.raises(SystemExit), reported_mistakes():
        data.queries  # noqa: B018 (what Hydra's instantiate reads)
    assert capsys.readouterr().err.startswith("data.queries: no value; this configuration needs it on the command line")


def test_report_of_a_folder_that_is_not_a_run(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["report.py", str(tmp_path)])
    with pytest.raises(SystemExit) as stopped:
        runpy.run_path(str(ROOT / "report.py"), run_name="__main__")
    assert stopped.value.code == 1
    assert capsys.readouterr().err == f"no results.csv in {tmp_path} or below it: not a finished evaluation run\n"


def test_a_mistake_in_a_job_of_a_multirun_is_raised_for_hydra_to_print_without_a_traceback(monkeypatch):
    monkeypatch.setattr(cli, "in_multirun", lambda: True)
    with pytest.raises(Mistake, match=r"^model.weights: not found$") as raised, reported_mistakes():
        raise FileNotFoundError("model.weights: not found")
    assert raised.value.__cause__ is None  # Hydra prints the message alone


@pytest.mark.parametrize(
    ("arguments", "expected"),
    [
        (["max_epochs=2"], [r"^max_epochs: unknown key; .*; did you mean trainer.max_epochs\?"]),
        (  # a parameter of the node's target that its YAML does not set: added with +
            ["trainer.gradient_clip_val=1"],
            [r"a parameter of lightning.Trainer that the config does not set is added with \+trainer.gradient_"],
        ),
        (  # in a sweep, every mistyped key at once, a sweep's key by its first value
            ["-m", "loss=ap,triplet", "trainer.max_epoch=1,2", "sampler.anchor=3"],
            [
                r"^trainer.max_epoch: .*max_epochs\? \(the command line's trainer.max_epoch=1\)",
                r"^sampler.anchor: .*anchors\?",
            ],
        ),
        (["debug=quick", "trainer.max_epochs=3", "+trainer.gradient_clip_val=1", "module.loss.bins=3", "loss=ap"], []),
    ],
)
def test_an_override_of_a_key_the_config_lacks_names_the_nearest(arguments, expected):
    found = unknown_override_keys(CONFIGS, "train", arguments)
    assert len(found) == len(expected) and all(re.search(p, line) for p, line in zip(expected, found)), found


def test_the_config_is_composed_only_for_a_key_that_is_surely_absent(monkeypatch):
    """Composing costs half a second a run: group options and keys whose first part is a top-level
    key and whose other parts the config files hold compose nothing here."""

    def composed(*_):
        raise AssertionError("composed")

    monkeypatch.setattr(cli, "composed", composed)
    assert unknown_override_keys(CONFIGS, "train", ["debug=quick", "trainer.max_epochs=3", "model/backbone=timm"]) == []
    for mistyped in ("trainer.max_epoch=2", "max_epochs=2"):
        with pytest.raises(AssertionError, match="composed"):
            unknown_override_keys(CONFIGS, "train", [mistyped])


def test_a_group_s_options_are_those_of_the_shipped_and_the_user_s_config_folders(tmp_path):
    (tmp_path / "model").mkdir()
    (tmp_path / "model" / "mine.yaml").write_text("name: mine\n")
    mine = ["--config-dir", str(tmp_path)]
    assert group_override_problems(CONFIGS, "evaluate", [*mine, "model=mine"]) == []
    [refused] = group_override_problems(CONFIGS, "evaluate", ["model=mine"])
    assert refused.startswith("model=mine: no such option of model (its options: apgem, ")
    # additions, deletions, Hydra's own groups, an optional group set to null and nested groups pass
    passing = ["+loss=ap", "~baselines", "hydra/launcher=joblib_local", "sfm/features=kapture", "hparams_search=null"]
    assert group_override_problems(CONFIGS, "train", passing) == []
    [swept] = group_override_problems(CONFIGS, "train", ["-m", "loss=ap,tripplet", "optimizer=adam"])
    assert swept.startswith("loss=tripplet: no such option of loss; did you mean triplet? (its options: ap, ")
    assert swept.endswith("(the command line's loss=ap,tripplet)")
    [missing] = group_override_problems(CONFIGS, "export", ["optimizer=adamw"])
    assert missing.startswith("optimizer: export has no config group optimizer; it is train's")


def test_a_device_is_named_as_typed_with_its_choices():
    assert device_problems(["device=cuda:1", "device=auto", "hydra.job.chdir=false"]) == []
    assert device_problems(["-m", "device=cpu,gpu,mps"]) == [
        f"device={name}: no such device; choose auto (a GPU when there is one), cpu, cuda or cuda:N"
        for name in ("gpu", "mps")
    ]
