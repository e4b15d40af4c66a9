"""Every option of every config group composes into an entry point that uses it, and every object
its YAML names (`_target_`) is built from it; where building needs what a fresh machine does not
have (published weights, a dataset, a torch.hub repository, a GPU, a value the user must give),
the error names it.

A nested group (``model/backbone``) is chosen under an option of its parent that lists it in its
defaults (``model=gem model/backbone=timm``), at the package that option gives it."""

import re
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
ENTRY_POINTS = ("evaluate", "train")
#: Not groups of the entry points: Hydra's launchers and sweepers (Hydra builds them; tests/training/test_sweeps.py).
NOT_GROUPS = {"hydra"}
#: A defaults-list entry: ``- [optional] group[@package]: option``.
DEFAULT_ENTRY = re.compile(r"^\s*-\s*(?:optional\s+)?/?([\w/]+)(@[\w.]+)?\s*:\s*[\w\-]+", re.M)
#: What building may need that a fresh machine lacks, and the words its error names it with.
NEEDS_WHAT_IS_NOT_HERE = {
    "MissingWeightsError": r"model '[^']+': (weight file not found|no model.weights path is set)",
    "DatasetNotFoundError": r"kapture folder not found: .*expects, under the data root",
    "FileNotFoundError": r"torch.hub repo '[^']+' is not in torch.hub's cache .* nothing is downloaded here",
    "MisconfigurationException": r"GPU|gpu|cuda|CUDA",
}
#: Targets whose building does a job, not a check: the synthetic scene renders itself.
NOT_BUILT = {"locretrieval.scene.datasets.load_synthetic_dataset"}


def options(group: str) -> list[str]:
    return sorted(path.stem for path in (CONFIGS / group).glob("*.yaml"))


def groups() -> list[str]:
    folders = (path.relative_to(CONFIGS) for path in CONFIGS.rglob("*") if path.is_dir())
    return sorted(str(folder) for folder in folders if folder.parts[0] not in NOT_GROUPS and options(str(folder)))


def choices(group: str) -> list[tuple[list[str], str]]:
    """How ``group`` is chosen: ``(overrides choosing its hosts, its override key)``, one per parent
    option that lists it in its defaults (a top-level group: chosen by its name)."""
    parts = group.split("/")
    if len(parts) == 1:
        return [([], group)]
    found = []
    for cut in range(len(parts) - 1, 0, -1):
        parent, relative = "/".join(parts[:cut]), "/".join(parts[cut:])
        for option in options(parent):
            for entry in DEFAULT_ENTRY.finditer((CONFIGS / parent / f"{option}.yaml").read_text()):
                if entry.group(1) != relative:
                    continue
                package = entry.group(2)
                key = group + (f"@{parent.replace('/', '.')}.{package[1:]}" if package else "")
                found += [([*hosts, f"{parent_key}={option}"], key) for hosts, parent_key in choices(parent)]
    return found


def composed(group: str, option: str) -> tuple[DictConfig, list[str]]:
    """The first entry point composed with ``option`` of ``group`` and the keys the option sets: its
    package (the defaults entry's, its ``# @package`` header's, or its group's), or for a
    ``@package _global_`` option (a preset) the top-level keys it sets."""
    text = (CONFIGS / group / f"{option}.yaml").read_text()
    preset = [key for key in (OmegaConf.create(text) or {}) if key not in ("defaults", *NOT_GROUPS)]
    errors = []
    for hosts, key in choices(group):
        for entry_point in ENTRY_POINTS:
            overrides = [*hosts, f"{key}={option}", "paths.root_dir=/nonexistent"]
            try:
                cfg = compose(entry_point, overrides=overrides, return_hydra_config=True)
            except Exception as error:  # this entry point does not have the group, or the host
                errors.append(f"{entry_point} {overrides}: {str(error).splitlines()[0]}")
                continue
            header = re.search(r"^# @package (\S+)", text, flags=re.M)
            if header and header.group(1) == "_global_":
                return cfg, preset
            if "@" in key:
                return cfg, [key.split("@", 1)[1]]
            return cfg, [header.group(1) if header else group.replace("/", ".")]
    pytest.fail(f"{group}={option} composes into no entry point:\n" + "\n".join(errors))


def targets(node) -> list[DictConfig]:
    """The outermost nodes with a ``_target_`` in ``node`` (itself, or below it)."""
    if isinstance(node, DictConfig):
        if "_target_" in node:
            return [node]
        return [found for key in node for found in targets(node._get_node(key))]
    if isinstance(node, ListConfig):
        return [found for item in node for found in targets(item)]
    return []


def build(node: DictConfig) -> object | None:
    """``instantiate(node)``, or None where it needs what is not here (`NEEDS_WHAT_IS_NOT_HERE`,
    checked to name it)."""
    try:
        return instantiate(node)
    except MissingMandatoryValue as error:  # ``???``: the user gives it (model.target of model=callable)
        assert "Missing mandatory value" in str(error)
        return None
    except InstantiationException as error:
        cause = error.__cause__
        pattern = NEEDS_WHAT_IS_NOT_HERE.get(type(cause).__name__)
        if pattern is None or not re.search(pattern, str(cause), flags=re.S):
            raise
        return None


CASES = [(group, option) for group in groups() for option in options(group)]


@pytest.mark.parametrize(("group", "option"), CASES, ids=[f"{group}={option}" for group, option in CASES])
def test_every_option_composes_and_builds(group, option, tmp_path):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg, packages = composed(group, option)
    cfg.hydra.runtime.output_dir = str(tmp_path)  # the run folder, as a run sets it (checkpoints, loggers)
    HydraConfig.instance().set_config(cfg)
    for package in packages:
        node = OmegaConf.select(cfg, package)
        assert node is not None, f"{group}={option}: nothing at {package}"
        for target in targets(node):
            if target._target_ not in NOT_BUILT:
                build(target)


def test_every_group_is_found_with_its_nested_groups():
    found = groups()
    assert {"model", "model/backbone", "paradigms/local_sfm/map_matches", "groundtruth/definitions"} <= set(found)
    assert ([], "model") in choices("model")
    assert (["groundtruth=default"], "groundtruth/definitions@groundtruth.definitions.relative_pose") in choices(
        "groundtruth/definitions"
    )


def test_an_error_that_does_not_name_what_is_missing_fails():
    broken = OmegaConf.create({"_target_": "locretrieval.models.files.weights.check_weights_file", "path": 1})
    with pytest.raises(Exception):
        build(broken)
