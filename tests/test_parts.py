"""Only parts can be called: at every ``_target_`` the config groups accept, ``subprocess.Popen``,
``os.system``, ``builtins.open`` (``mode: w``) and ``this`` are refused before anything is imported
or called, by the entry points' check and by every builder that resolves a target itself."""

import re
import sys
from pathlib import Path

import pytest
import yaml
from helpers import CONFIGS, compose_config, set_limits, trust_packages
from omegaconf import OmegaConf

from locretrieval.config import ConfigError, check_node, check_run_config
from locretrieval.groundtruth.compute import definition_class
from locretrieval.models.networks import build_pooling, pooling_settings
from locretrieval.models.trainable.backbones import backbone_of
from locretrieval.paradigms.base import paradigm_of
from locretrieval.parts import PART_GROUPS, pattern_of, resolve_part

#: What a hostile config names: a process, a shell command, a file opened for writing, a module that prints on import.
HOSTILE_TARGETS = ["subprocess.Popen", "os.system", "builtins.open", "this"]
#: Not importable at all: ``this`` prints the Zen of Python when imported.
NEVER_IMPORTED = "this"


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


def configured_targets() -> dict[str, set[str]]:
    """Every config key holding a ``_target_`` and the targets the configs give it: each YAML file's at its
    package (its group's path, its ``# @package`` header, the root for ``_global_`` presets), and the
    composed entry points' (where defaults lists place an option, e.g. ``...weights.csi``)."""
    found: dict[str, set[str]] = {}
    for path in CONFIGS.rglob("*.yaml"):
        group = path.relative_to(CONFIGS).parent.parts
        if group[:1] == ("hydra",):
            continue
        text = path.read_text()
        header = re.search(r"^# @package (\S+)", text, flags=re.M)
        prefix = "" if not group or "_global_" in text else header.group(1) if header else ".".join(group)
        for key, target in targets_below(yaml.safe_load(text) or {}, prefix):
            found.setdefault(key, set()).add(target)
    for name in ("evaluate", "train"):
        composed = OmegaConf.to_container(compose_config(name, "paths.root_dir=/nonexistent"), resolve=False)
        for key, target in targets_below(composed):
            found.setdefault(key, set()).add(target)
    return found


@pytest.fixture(scope="module")
def target_keys() -> dict[str, set[str]]:
    return configured_targets()


def test_every_target_the_configs_name_is_a_part_of_its_group(target_keys):
    assert {
        "model",
        "model.backbone",
        "model.pooling",
        "trainer",
        "trainer.plugins[0]",
        "callbacks.best_checkpoint",
    } <= set(target_keys)
    assert len(target_keys) >= 40
    for key, targets in target_keys.items():
        for target in targets:
            resolve_part(target, key)  # raises for a table that forgot a group's base class or library
    unlisted = {key for key in target_keys if pattern_of(key) is None}
    assert unlisted <= {  # a group file's own package, not where a defaults list places its options
        "paradigms", "paradigms.approximation.weights", "paradigms.weights", "paradigms.map_matches",
        "groundtruth.definitions", "data.render.environments", "subsets.mask_sources",
    }, unlisted  # fmt: skip
    assert len(PART_GROUPS) >= 30


def test_hostile_targets_are_refused_at_every_key_before_anything_is_imported(target_keys):
    for key in target_keys:
        for target in HOSTILE_TARGETS:
            with pytest.raises(ConfigError, match=rf"^{re.escape(key)}._target_: {re.escape(target)} is not a part"):
                resolve_part(target, key)
    assert NEVER_IMPORTED not in sys.modules


@pytest.mark.parametrize("entry_point", ["evaluate", "train"])
def test_the_entry_points_check_refuses_them_anywhere_in_the_config(entry_point, tmp_path, monkeypatch):
    """A run's check (`check_run_config`, what evaluate() and train.py do first) at every target of the composed
    config: a file opened with mode w stays as it was, no process starts."""
    set_limits(monkeypatch)  # the limits the check sets for the run end with the test
    victim, marker = tmp_path / "victim.txt", tmp_path / "pwned"
    victim.write_text("kept")
    cfg = compose_config(entry_point, "paths.root_dir=/nonexistent")
    keys = [key for key, _ in targets_below(OmegaConf.to_container(cfg, resolve=False))]
    assert len(keys) >= (10 if entry_point == "evaluate" else 25)
    hostile_nodes = {
        "subprocess.Popen": {"args": ["touch", str(marker)]},
        "os.system": {"command": f"touch {marker}"},
        "builtins.open": {"file": str(victim), "mode": "w"},
        "this": {},
    }
    for number, key in enumerate(keys):  # each key one of them in turn (every one at every key: resolve_part's test)
        target, arguments = list(hostile_nodes.items())[number % len(hostile_nodes)]
        hostile = cfg.copy()
        OmegaConf.set_struct(hostile, False)
        OmegaConf.select(hostile, key).update({"_target_": target, **arguments})
        with pytest.raises(ConfigError, match=rf"^{re.escape(key)}._target_: {re.escape(target)} is not a part"):
            check_run_config(hostile)
    assert victim.read_text() == "kept" and not marker.exists() and NEVER_IMPORTED not in sys.modules


def test_builders_that_resolve_targets_themselves_refuse_them_too():
    """A checkpoint's architecture (backbone, pooling), a ground-truth definition, a paradigm, a node checked
    by keys: each resolves its target through the same check, before importing it."""
    calls = {
        "model.backbone": lambda target: backbone_of({"_target_": target, "args": ["true"]}),
        "model.pooling": lambda target: build_pooling(8, {"_target_": target}),
        "groundtruth.definitions.mine": lambda target: definition_class(target, "groundtruth.definitions.mine"),
        "paradigms.mine": lambda target: paradigm_of({"_target_": target}, "paradigms.mine", ["mine"]),
        "sfm.features": lambda target: check_node(OmegaConf.create({"_target_": target, "mode": "w"}), "sfm.features"),
    }
    for key, call in calls.items():
        for target in HOSTILE_TARGETS:
            with pytest.raises(ConfigError, match=rf"{re.escape(key)}._target_: {re.escape(target)} is not a part"):
                call(target)
    with pytest.raises(ConfigError, match=r"model.pooling._target_: .*'os.system'.* is not an import path"):
        pooling_settings({"_target_": {"_target_": "os.system"}})
    assert NEVER_IMPORTED not in sys.modules


def test_a_users_package_is_trusted_by_name_and_its_parts_still_checked(tmp_path, monkeypatch):
    (tmp_path / "my_parts.py").write_text(
        "import torch\n\n"
        "class MaxPooling(torch.nn.Module):\n"
        "    def __init__(self, channels):\n        super().__init__()\n        self.output_dim = channels\n\n"
        "class NotAModule:\n    pass\n\n"
        "def helper():\n    pass\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ConfigError, match=r"my_parts.MaxPooling is not a part: .*limits.trusted_packages"):
        resolve_part("my_parts.MaxPooling", "model.pooling")
    assert "my_parts" not in sys.modules  # refused before its import
    trust_packages(monkeypatch, "my_parts")
    assert build_pooling(16, {"_target_": "my_parts.MaxPooling"}).output_dim == 16
    with pytest.raises(
        ConfigError, match=r"my_parts.NotAModule is not a part of model.pooling: a part there is a Module"
    ):
        resolve_part("my_parts.NotAModule", "model.pooling")
    with pytest.raises(ConfigError, match=r"my_parts.helper is not a part of model.backbone: not a class"):
        resolve_part("my_parts.helper", "model.backbone")
    with pytest.raises(ConfigError, match=r"locretrieval.config.os.system is not a part of .*defined in posix"):
        resolve_part("locretrieval.config.os.system", "model.backbone")  # imported into an allowed module
    assert resolve_part("locretrieval.scene.datasets.load_dataset", "data").__name__ == "load_dataset"  # -> Scene
    with pytest.raises(ConfigError, match=r"locretrieval.cache.save_arrays is not a part of data: a function there"):
        resolve_part("locretrieval.cache.save_arrays", "data")
    assert Path(sys.modules["my_parts"].__file__).parent == tmp_path
