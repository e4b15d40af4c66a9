"""Every config key the README and docs name exists (a removed or renamed key fails here);
the dated sections of docs/results.md and the changelog, which quote the commands of their
version, are left out."""

import re
from pathlib import Path

import yaml
from helpers import compose_config
from hydra.conf import HydraConf
from omegaconf import OmegaConf

from locretrieval.config import MOVED_KEYS

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
#: A heading of a dated section, e.g. ``## Training: what it buys on five scenes (0.7.0)`` or
#: ``### ... (2026-11-26, after 0.11.0)``: its commands are those of its version.
DATED_HEADING = re.compile(r"^(#+) .*\((?:\d+\.\d+\.\d+|\d{4}-\d{2}-\d{2})[^)]*\)\s*$")


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
#: be new) or in backticks, or a family of keys (`subsets.maskrcnn_*`); not a file name (`report.py`).
KEY = re.compile(r"(?<![\w./$+-])~?((?:%s)(?:\.[A-Za-z_][A-Za-z0-9_]*)+(?:\.?\*)?)(?![\w/])" % "|".join(GROUPS))
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


def code_spans(text: str) -> list[str]:
    """The fenced code blocks of a Markdown ``text`` and its inline code spans outside them."""
    fenced = re.findall(r"```.*?```", text, flags=re.S)
    return fenced + re.findall(r"`([^`]+)`", re.sub(r"```.*?```", "", text, flags=re.S))


def named_keys(text: str) -> set[str]:
    spans = code_spans(text)
    return {match for span in spans for match in KEY.findall(span) if match.rsplit(".", 1)[-1] not in FILE_SUFFIXES}


def undated(text: str) -> str:
    """``text`` without its dated sections (`DATED_HEADING`), each up to the next heading of its
    level or above, and without its rename notes (a paragraph ``Renamed in <version> ...``: the
    spellings of before)."""
    text = re.sub(r"(?ms)^Renamed in \d.*?(?:\n\s*\n|\Z)", "", text)
    kept, dated_level = [], None
    for line in text.splitlines():
        heading = re.match(r"^(#+) ", line)
        if heading and dated_level is not None and len(heading.group(1)) <= dated_level:
            dated_level = None
        if dated_level is None and (dated := DATED_HEADING.match(line)):
            dated_level = len(dated.group(1))
        if dated_level is None:
            kept.append(line)
    return "\n".join(kept)


def exists(key: str, keys: set[tuple[str, ...]]) -> bool:
    """Whether ``key`` is a config key, a moved one (`MOVED_KEYS`: a rename the text explains),
    or for a family (``prefix*``) whether one of those starts with its prefix."""
    if not key.endswith("*"):
        return tuple(key.split(".")) in keys or key in MOVED_KEYS
    prefix = key.rstrip("*")
    return any(".".join(path).startswith(prefix) for path in keys) or any(
        moved.startswith(prefix) for moved in MOVED_KEYS
    )


def test_every_config_key_the_documents_name_exists():
    keys = config_keys()
    missing = []
    for document in DOCUMENTS:
        for key in sorted(named_keys(undated(document.read_text()))):
            if not exists(key, keys):
                missing.append(f"{document.relative_to(ROOT)}: {key}")
    assert missing == []


def test_the_scan_finds_a_removed_key():
    assert "sfm.features.type" in named_keys("run `python evaluate.py sfm.features.type=kapture` there")
    assert named_keys("`python report.py run`, `+model.pooling.out_channels=1024`") == set()  # a script; an added key
    assert ("sfm", "features", "type") not in config_keys() and ("sfm", "features", "name") in config_keys()
    assert ("hydra", "searchpath") in config_keys() and ("hydra", "search_path") not in config_keys()


def test_dated_sections_are_left_out_up_to_the_next_heading_of_their_level():
    text = "\n".join(
        [
            "## Now",
            "`sfm.kept`",
            "## Then (0.7.0)",
            "`sfm.old`",
            "### Detail",
            "`sfm.older`",
            "## Published datasets",
            "`sfm.also_kept`",
            "### Lever (2026-11-25)",
            "`sfm.gone`",
        ]
    )
    assert named_keys(undated(text)) == {"sfm.kept", "sfm.also_kept"}
    notes = "Renamed in 0.6.0: `training.batch.*` -> `sampler.*`.\n\n`sfm.kept`"
    assert named_keys(undated(notes)) == {"sfm.kept"}


def test_a_family_of_keys_exists_when_one_key_starts_with_its_prefix():
    keys = config_keys()
    assert named_keys("`subsets.maskrcnn_*`, `sfm.features.*`") == {"subsets.maskrcnn_*", "sfm.features.*"}
    assert exists("subsets.maskrcnn_*", keys) and exists("sfm.features.*", keys)  # moved keys; sfm.features.name
    assert not exists("sampler.batch_*", keys) and not exists("training.augment.*", keys)


#: The groups a user picks an option of on the command line (``loss=ap``); ``default`` options aside.
CHOSEN_GROUPS = ("model", "loss", "optimizer", "scheduler", "memory", "miner", "data", "finetune", "trainer", "debug")


def test_every_option_of_the_command_line_groups_is_named_in_the_documents():
    spans = [span for document in DOCUMENTS for span in code_spans(document.read_text())]
    unnamed = [
        f"{group}={path.stem}"
        for group in CHOSEN_GROUPS
        for path in sorted((CONFIGS / group).glob("*.yaml"))
        if not any(re.search(rf"(?<![\w.]){re.escape(path.stem)}(?!\w)", span) for span in spans)
    ]
    assert unnamed == []
