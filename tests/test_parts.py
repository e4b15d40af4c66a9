"""What a ``_target_`` may name, by where its config comes from (locretrieval.parts): a config the user
runs is code and names anything, their own package's classes included, with no trust setting; the
architecture a checkpoint records is data, and names only parts (no process, shell command, file
opened for writing or module that prints on import), no interpolation, before anything is imported."""

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import helpers
import pandas as pd
import pytest
import torch
import yaml
from helpers import CONFIGS, compose_config, set_limits
from omegaconf import OmegaConf

from locretrieval.config import ConfigError
from locretrieval.export.network import descriptor_from_checkpoint
from locretrieval.models.files.weights import save_checkpoint
from locretrieval.models.networks import POOLING
from locretrieval.parts import check_recorded, import_part, resolve_recorded

#: What a hostile file names: a process, a shell command, a file opened for writing, a module that prints on import.
HOSTILE_TARGETS = ["subprocess.Popen", "os.system", "builtins.open", "this"]
#: Not importable at all: ``this`` prints the Zen of Python when imported.
NEVER_IMPORTED = "this"
ROOT = Path(__file__).resolve().parents[1]


def targets_below(node, key: str = ""):
    """``(key, target)`` of every ``_target_`` in plain data ``node``, at its full key below ``key``."""
    if isinstance(node, dict):
        for name, value in node.items():
            if name == "_target_":
                yield key, value
            elif name not in ("defaults", "hydra"):
                yield from targets_below(value, f"{key}.{name}" if key else str(name))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from targets_below(value, f"{key}[{index}]")


def test_every_target_the_shipped_configs_name_imports():
    found = {}
    for path in CONFIGS.rglob("*.yaml"):
        if path.relative_to(CONFIGS).parts[0] != "hydra":
            found |= dict(targets_below(yaml.safe_load(path.read_text()) or {}, path.stem))
    for name in ("evaluate", "train"):
        found |= dict(targets_below(OmegaConf.to_container(compose_config(name, "paths.root_dir=/x"), resolve=False)))
    assert len(found) >= 40
    for key, target in found.items():
        import_part(target, key)  # a misspelt target in a shipped config fails here, naming its key


def hostile_checkpoint(path: Path, pooling: dict, preprocessing: dict | None = None) -> Path:
    """A locretrieval checkpoint of the trainable family recording ``pooling`` (and ``preprocessing``)."""
    backbone = {"_target_": "locretrieval.models.trainable.backbones.TimmBackbone", "name": "resnet18"}
    save_checkpoint(
        path,
        "trainable",
        {"backbone": backbone, "pooling": pooling, "whiten_dim": None},
        preprocessing or {"max_side": 160, "mean": [0.5] * 3, "std": [0.5] * 3},
        {"w": torch.zeros(1)},
    )
    return path


def test_a_checkpoints_architecture_names_parts_only_before_anything_is_imported(tmp_path):
    victim, marker = tmp_path / "victim.txt", tmp_path / "pwned"
    victim.write_text("kept")
    arguments = {
        "subprocess.Popen": {"args": ["touch", str(marker)]},
        "os.system": {"command": f"touch {marker}"},
        "builtins.open": {"file": str(victim), "mode": "w"},
        "this": {},
    }
    for number, target in enumerate(HOSTILE_TARGETS):
        checkpoint = hostile_checkpoint(tmp_path / f"{number}.pt", {"_target_": target, **arguments[target]})
        with pytest.raises(ConfigError, match=rf"architecture: pooling._target_: {re.escape(target)} is not a part"):
            descriptor_from_checkpoint(checkpoint)
    nested = {"_target_": "locretrieval.models.networks.GeMPooling", "p": {"_target_": "os.system", "command": "x"}}
    with pytest.raises(ConfigError, match=r"pooling.p._target_: os.system is not a part"):
        descriptor_from_checkpoint(hostile_checkpoint(tmp_path / "nested.pt", nested))
    assert victim.read_text() == "kept" and not marker.exists() and NEVER_IMPORTED not in sys.modules


def test_an_interpolation_in_a_checkpoints_record_is_refused_before_it_resolves(tmp_path, monkeypatch):
    """An interpolation that resolves only later (an environment variable the run sets afterwards, as
    ``PL_GLOBAL_SEED``) would hide a target from the check: a recorded config holds none."""
    monkeypatch.delenv("HIDDEN_TARGET", raising=False)
    hidden = hostile_checkpoint(tmp_path / "hidden.pt", {"_target_": "${oc.env:HIDDEN_TARGET,os.system}"})
    with pytest.raises(ConfigError, match=r"architecture.pooling._target_: '\$\{oc.env:HIDDEN_TARGET.*interpolation"):
        descriptor_from_checkpoint(hidden)
    in_preprocessing = hostile_checkpoint(
        tmp_path / "size.pt", {"_target_": "locretrieval.models.networks.GeMPooling"}, {"max_side": "${oc.env:X}"}
    )
    with pytest.raises(ConfigError, match=r"preprocessing.max_side: .* interpolation"):
        descriptor_from_checkpoint(in_preprocessing)


def test_the_hub_entry_refuses_a_hostile_checkpoint_in_a_fresh_process_with_a_named_error(tmp_path):
    checkpoint = hostile_checkpoint(tmp_path / "hostile.pt", {"_target_": "${oc.env:HIDDEN_TARGET,this}"})
    code = f"import torch; torch.hub.load({str(ROOT)!r}, 'locretrieval', weights={str(checkpoint)!r}, source='local')"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert "ConfigError: " in done.stderr and "is an interpolation" in done.stderr
    assert "Beautiful is better than ugly" not in done.stdout  # `this` never imported


def test_a_checkpoint_may_name_a_users_package_that_their_command_line_trusts(tmp_path, monkeypatch):
    (tmp_path / "my_parts.py").write_text(
        "import torch\n\n"
        "class MaxPooling(torch.nn.Module):\n"
        "    def __init__(self, channels):\n        super().__init__()\n        self.output_dim = channels\n\n"
        "class NotAModule:\n    pass\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    set_limits(monkeypatch)
    with pytest.raises(ConfigError, match=r"my_parts.MaxPooling is not a part: .*limits.trusted_packages"):
        check_recorded({"pooling": {"_target_": "my_parts.MaxPooling"}}, "x.pt: architecture", {"pooling": POOLING})
    assert "my_parts" not in sys.modules  # refused before its import
    set_limits(monkeypatch, trusted_packages=["my_parts"])
    assert resolve_recorded("my_parts.MaxPooling", "pooling", POOLING).__name__ == "MaxPooling"
    with pytest.raises(ConfigError, match=r"my_parts.NotAModule is not a part of pooling: a part there is a Module"):
        resolve_recorded("my_parts.NotAModule", "pooling", POOLING)
    with pytest.raises(
        ConfigError, match=r"locretrieval.config.os.system is not a part of backbone: .*defined in posix"
    ):
        resolve_recorded("locretrieval.config.os.system", "backbone")  # imported into an allowed module


TOY_PARADIGM = '''
    """A paradigm of a user's own package: each query at the pose of its top-ranked database image."""

    from dataclasses import dataclass

    import numpy as np

    from locretrieval.estimates import PoseEstimates
    from locretrieval.paradigms.base import Paradigm


    @dataclass
    class TopImage(Paradigm):
        def method_names(self):
            return ["top_image"]

        def run(self, scene, rankings, sfm, cache_dir):
            estimates = []
            for ranking in rankings:
                top, ks = ranking.indices[:, 0], list(self.k)
                qvec = scene.database.qvec[top][None].repeat(len(ks), 0)
                tvec = scene.database.tvec[top][None].repeat(len(ks), 0)
                failures = np.full((len(ks), len(top)), "", dtype=object)
                outcome = PoseEstimates(ranking.name, ranking.kind, "top_image", "top_image", ks, qvec, tvec, failures)
                estimates.append(outcome)
            return estimates
'''


@pytest.mark.slow
def test_a_new_part_group_is_one_module_and_one_yaml_run_from_the_command_line_without_trust(tmp_path):
    """A user adds a paradigm with a module of their package and a YAML in their config folder (Hydra's
    search path), and runs the documented command with it: nothing to edit in locretrieval, no trust
    setting; its results equal paradigm 1 (EWB) at k=1, as the pose of the top-ranked image is."""
    package = tmp_path / "my_package"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "toy.py").write_text(textwrap.dedent(TOY_PARADIGM))
    (tmp_path / "my_configs" / "paradigms").mkdir(parents=True)
    (tmp_path / "my_configs" / "paradigms" / "top_image.yaml").write_text(
        "_target_: my_package.toy.TopImage\nenabled: true\nk: [1]\n"
    )
    run = tmp_path / "run"
    command = [
        sys.executable, str(ROOT / "evaluate.py"), f"hydra.searchpath=[file://{tmp_path / 'my_configs'}]",
        "+paradigms@paradigms.top_image=top_image", f"hydra.run.dir={run}", f"paths.root_dir={tmp_path}",
        "paradigms.local_sfm.enabled=false", "paradigms.global_sfm.enabled=false", "paradigms.approximation.k=[1]",
        "groundtruth.enabled=[relative_pose]", "report.figure_formats=[]", "report.scene_view.enabled=false",
        "report.gallery.worst=0", "report.gallery.random=0", "output.ltvl=false", "subsets.dynamic_masks=[]",
        *helpers.TINY_SCENE,
    ]  # fmt: skip
    environment = {**os.environ, "PYTHONPATH": str(tmp_path)}
    done = subprocess.run(command, capture_output=True, text=True, timeout=600, env=environment, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    results = pd.read_csv(run / "results.csv").query("subset == 'all'")
    columns = ["ranking", "position_threshold_m", "localized_pct"]
    mine = results[results["paradigm"] == "top_image"][columns].sort_values(columns[:2]).reset_index(drop=True)
    ewb = results[(results["paradigm"] == "approximation") & (results["method"] == "ewb")][columns]
    assert len(mine) == 3 * 3  # densevlad, the ground truth and random, three thresholds
    pd.testing.assert_frame_equal(mine, ewb.sort_values(columns[:2]).reset_index(drop=True))
