"""Every config key the README and docs name exists (a removed or renamed key fails here);
the dated sections of docs/results.md and the changelog, which quote the commands of their
version, are left out. No doc under docs/ names a date, a commit or a past version: the
changelog does."""

import re
from pathlib import Path

import yaml
from helpers import compose_config
from hydra.conf import HydraConf
from omegaconf import OmegaConf

from locretrieval.config import MOVED_KEYS

ROOT = Path(__file__).resolve().parents[2]
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
    level or above, and without its rename notes (a paragraph ``Renamed keys ...``: the spellings
    of before)."""
    text = re.sub(r"(?ms)^Renamed keys\b.*?(?:\n\s*\n|\Z)", "", text)
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
    notes = "Renamed keys: `training.batch.*` -> `sampler.*`.\n\n`sfm.kept`"
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


#: A date (``2026-11-27``).
DATE = re.compile(r"\b\d{4}-\d{2}-\d{2}\b")
#: A commit hash: 7 to 40 hex digits with a digit and a letter (so no number and no word).
COMMIT = re.compile(r"\b(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b")
#: A published weight file named as torch.hub names them, ``<name>-<first hex digits of its SHA-256>.pth``
#: (``resnet50-11ad3fa6.pth``): the digits are the file's hash, which torch.hub checks, not a commit.
HUB_FILE_HASH = re.compile(r"(?<=-)[0-9a-f]+(?=\.pth?\b)")
#: A version: ``0.11.0``; ``0.12`` after a word that dates it (``in 0.12``, ``since 0.12``, not a
#: measure: ``in 0.25 m``); ``0.12 and earlier``; ``v0.12``.
VERSION = re.compile(
    r"(?i)(?<![\w.])(?P<full>v?\d+\.\d+\.\d+)(?!\.?\w)"
    r"|\b(?:since|before|after|until|in|as of|version|release|locretrieval)\s+(?P<dated>v?0\.\d+)(?!\.?\d)"
    r"(?!\s*(?:%|(?:s|ms|min|h|m|km|cm|mm|px|deg|points?|units?|x|[KMG]i?B)\b))"
    r"|\b(?P<bounded>v?0\.\d+)\s+(?:and|or)\s+(?:earlier|later|before|after)\b"
    r"|\b(?P<prefixed>v0\.\d+)\b"
)
#: Other packages and formats whose versions a document gives (``torch 2.13.0``, ``kapture 1.1``).
THIRD_PARTY = (
    "torch",
    "torchvision",
    "pycolmap",
    "colmap",
    "optuna",
    "numpy",
    "scipy",
    "numba",
    "timm",
    "lightning",
    "hydra-core",
    "hydra",
    "omegaconf",
    "sqlalchemy",
    "kapture-localization",
    "kapture",
    "onnxruntime",
    "onnx",
    "opset",
    "python",
    "cuda",
)
#: What a number a version pattern matched follows when it is not ours: a package of `THIRD_PARTY`
#: (``torch>=2.13.0``) or a section of a paper (``Sec. 3.6.1``), then possibly other numbers of a
#: list (``Sec. 3.6.1, 3.6.2``).
NOT_OURS = re.compile(
    r"(?i)(?:\b(?:%s)\s*(?:[<>=!~]=?\s*)?|\b(?:Sec\.|Section|Table|Fig\.|Eq\.)\s*)"
    r"(?:v?\d+(?:\.\d+)*(?:'s)?(?:,\s*|\s+(?:and|or|to)\s+))*$" % "|".join(map(re.escape, THIRD_PARTY))
)


def history(text: str) -> list[tuple[int, str]]:
    """The dates, commit hashes and versions of locretrieval ``text`` names, each with its line
    (a match may span a line break): a document says what the code does now, and CHANGELOG.md
    when it changed."""
    hub_hashes = {m.span() for m in HUB_FILE_HASH.finditer(text)}
    found = [*DATE.finditer(text), *(m for m in COMMIT.finditer(text) if m.span() not in hub_hashes)]
    for m in VERSION.finditer(text):
        name = next(group for group in ("full", "dated", "bounded", "prefixed") if m.group(group))
        if not NOT_OURS.search(text[max(0, m.start(name) - 120) : m.start(name)]):
            found.append(m)
    return [
        (text.count("\n", 0, m.start()) + 1, " ".join(m.group().split()))
        for m in sorted(found, key=lambda m: m.start())
    ]


def test_no_document_names_a_date_a_commit_or_a_past_version():
    named = [
        f"{document.relative_to(ROOT)}:{line}: {found}"
        for document in sorted((ROOT / "docs").rglob("*.md"))
        for line, found in history(document.read_text())
    ]
    assert named == []


def test_the_history_scan_finds_dates_commits_and_our_versions_only():
    assert history("measured 2026-11-27 at 8d42c20,\nbefore 0.12 (as 0.11.0 and earlier)") == [
        (1, "2026-11-27"),
        (1, "8d42c20"),
        (2, "before 0.12"),
        (2, "0.11.0"),
    ]
    assert [
        found for _, found in history("since 0.5.0, in\n0.12's layout, v0.9, 0.10 or later; locretrieval 0.12")
    ] == [
        "0.5.0",
        "in 0.12",
        "v0.9",
        "0.10 or later",
        "locretrieval 0.12",
    ]
    third_party = "torch 2.13.0 with torchvision 0.28.0, `pycolmap>=4.2.1`, Optuna 4.0.0, kapture 1.1, Python 3.11.4"
    papers = "Sec. 3.6.1, 3.6.2 and 4.1.2's discussion; Table 1"
    measures = "in 0.25 m, ratio 0.5 in the study, 0.1 to 0.6, (0.86), since 0.5 s, 10.4-13.2 images/s"
    files = "`resnet50-11ad3fa6.pth`, `maskrcnn_resnet50_fpn_coco-bf2d0c1e.pth`, a 1234567-byte file, `decade`"
    assert history(" ".join([third_party, papers, measures, files])) == []
