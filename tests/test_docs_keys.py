"""Every config key the README and docs name exists (a removed or renamed key fails here);
the dated results and the changelog, which quote the commands of their version, are left out."""

import re
from pathlib import Path

import yaml
from helpers import compose_config
from hydra.conf import HydraConf
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LEFT_OUT = {"results.md"}  # dated: each section's commands are those of its version


def _paths(node, prefix: tuple[str, ...]):
    yield prefix
    if isinstance(node, dict):
        for key, value in node.items():
            if key != "defaults":
                yield from _paths(value, (*prefix, str(key)))


def config_keys() -> set[tuple[str, ...]]:
    """Every key path any config file defines, under the package it lands in (its group's path, the
    package of its ``@package`` header, or the root for ``@package _global_`` files and the primary
    configs), those of the composed entry points (a default placed by its defaults list) and Hydra's
    own."""
    keys = set(_paths(OmegaConf.to_container(OmegaConf.structured(HydraConf)), ("hydra",)))
    for path in CONFIGS.rglob("*.yaml"):
        text = path.read_text()
        group = path.relative_to(CONFIGS).parent.parts
        package = re.search(r"^# @package (\S+)", text, flags=re.M)  # the file's header: where it lands
        if "@package _global_" in text or not group:
            prefix: tuple[str, ...] = ()
        elif package:
            prefix = tuple(package.group(1).split("."))  # e.g. module.loss
        else:
            prefix = group
        keys |= set(_paths(yaml.safe_load(text) or {}, prefix))
        if group and group[0] == "model" and path.name != "preprocessing":  # model@validation_references.<name>
            keys |= set(_paths(yaml.safe_load(text) or {}, ("validation_references", "densevlad")))
    for name in ("evaluate", "train"):  # where defaults lists place a group's options (weights@...weights.csi)
        keys |= set(_paths(OmegaConf.to_container(compose_config(name, "paths.root_dir=/nonexistent")), ()))
    return keys


GROUPS = sorted(
    {path.name for path in CONFIGS.iterdir() if path.is_dir()}
    | {"training", "report", "retrieval", "metrics", "baselines", "output"}
)
#: `group.key[.key...]` in a command (an override, possibly `~`-prefixed; `+` adds a key, so it may
#: be new) or in backticks; not a file name (`report.py`).
KEY = re.compile(r"(?<![\w./$+-])~?((?:%s)(?:\.[A-Za-z_][A-Za-z0-9_]*)+)(?![\w/])" % "|".join(GROUPS))
FILE_SUFFIXES = {
    "py",
    "md",
    "yaml",
    "csv",
    "txt",
    "json",
    "npz",
    "npy",
    "html",
    "png",
    "jpg",
    "gz",
    "ckpt",
    "pth",
    "sh",
}


def named_keys(text: str) -> set[str]:
    spans = re.findall(r"`([^`]+)`", text) + re.findall(r"```.*?```", text, flags=re.S)
    return {match for span in spans for match in KEY.findall(span) if match.rsplit(".", 1)[-1] not in FILE_SUFFIXES}


def test_every_config_key_the_documents_name_exists():
    keys = config_keys()
    missing = []
    for document in DOCUMENTS:
        if document.name in LEFT_OUT:
            continue
        for key in sorted(named_keys(document.read_text())):
            if tuple(key.split(".")) not in keys:
                missing.append(f"{document.relative_to(ROOT)}: {key}")
    assert missing == []


def test_the_scan_finds_a_removed_key():
    assert "sfm.features.type" in named_keys("run `python evaluate.py sfm.features.type=kapture` there")
    assert named_keys("`python report.py run`, `+model.pooling.out_channels=1024`") == set()  # a script; an added key
    assert ("sfm", "features", "type") not in config_keys() and ("sfm", "features", "name") in config_keys()
    assert ("hydra", "searchpath") in config_keys() and ("hydra", "search_path") not in config_keys()
