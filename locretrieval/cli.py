"""What the entry points (evaluate.py, train.py, report.py) share: one clear screen per mistake.

A mistake of the project's own kinds (`MISTAKES`: a config key or value, `ConfigError`; a data,
weight or cache file that cannot be used, `DataFileError`; a missing input file or folder,
`FileNotFoundError`; a value the config leaves to the command line, ``???``) ends the run with
its message and exit status 1, without a traceback (`reported_mistakes`); ``HYDRA_FULL_ERROR=1``
shows the traceback, as it does for Hydra's own errors. A command-line override of a key the
config lacks is refused before Hydra composes it, naming the nearest keys (`check_command_line`):
Hydra's own refusal ("To append to your config use +key=value") points the wrong way for a typo.
"""

from __future__ import annotations

import contextlib
import difflib
import logging
import os
import re
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from hydra.errors import CompactHydraException
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from locretrieval.config import ConfigError, refuse_moved_keys, unknown_key
from locretrieval.errors import DataFileError
from locretrieval.resources import configs_dir

log = logging.getLogger(__name__)

#: The errors that are the user's to fix, reported by their message alone.
MISTAKES = (ConfigError, DataFileError, FileNotFoundError, MissingMandatoryValue)
#: The environment variable (Hydra's) that shows a mistake's traceback too.
FULL_ERROR_ENV = "HYDRA_FULL_ERROR"


class Mistake(CompactHydraException):
    """A mistake (`MISTAKES`) in one job of a multirun: Hydra prints its message without a
    traceback once the sweep ends, and a sweeper records it as the job's failure."""


def mistake_in(error: BaseException) -> BaseException | None:
    """The mistake ``error`` is, or the one Hydra's `instantiate` wrapped into it; ``None`` for any
    other error (a fault of the program: its traceback is shown)."""
    from hydra.errors import InstantiationException

    while isinstance(error, InstantiationException) and error.__cause__ is not None:
        error = error.__cause__
    return error if isinstance(error, MISTAKES) else None


def mistake_message(mistake: BaseException) -> str:
    """What the user reads: the mistake's message (a ``???`` value: the key and how to give it)."""
    if isinstance(mistake, MissingMandatoryValue):
        key = mistake.full_key or "a key"
        return f"{key}: no value; this configuration needs it on the command line ({key}=...)"
    return str(mistake)


@contextlib.contextmanager
def reported_mistakes() -> Iterator[None]:
    """Report a mistake raised inside (`mistake_in`) as one screen: its message on stderr (and in
    the job's log file), exit status 1, no traceback. In a job of a Hydra multirun it is raised
    again as a `Mistake`, so that the sweep's other jobs go on and Hydra reports it when the sweep
    ends. Every other error, and every error when ``HYDRA_FULL_ERROR=1``, passes unchanged."""
    try:
        yield
    except Exception as error:
        mistake = mistake_in(error)
        if mistake is None or os.environ.get(FULL_ERROR_ENV) == "1":
            raise
        message = mistake_message(mistake)
        log_to_files(message)
        if in_multirun():
            raise Mistake(message) from None
        sys.stderr.write(message.rstrip("\n") + "\n")
        raise SystemExit(1) from None


def in_multirun() -> bool:
    """Whether this process runs a job of a Hydra multirun."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def log_to_files(message: str) -> None:
    """``message`` as an error in the log files of the root logger (a Hydra job's ``<name>.log``),
    not on the console, where it is written once and plain."""
    record = log.makeRecord(log.name, logging.ERROR, __file__, 0, "%s", (message,), None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)


def check_command_line(config_dir: Path, config_name: str, arguments: Sequence[str]) -> None:
    """Refuse, as a mistake (`reported_mistakes`), the command line's overrides of keys that moved
    (`refuse_moved_keys`), of config groups the command lacks or options a group lacks
    (`group_override_problems`), of a ``device`` that is none (`device_problems`) and of keys the
    composed config lacks (`unknown_override_keys`), before Hydra runs it: Hydra's own messages
    list every option with its search path, advise ``+group=`` for a group the command does not have,
    and blame the key a refused value lands in (``sfm.matching.device``) rather than the one typed.
    ``config_dir``/``config_name``: the command's configs; ``arguments``: its command line."""
    with reported_mistakes():
        refuse_moved_keys(arguments)
        problems = [
            *group_override_problems(config_dir, config_name, arguments),
            *device_problems(arguments),
            *unknown_override_keys(config_dir, config_name, arguments),
        ]
        if problems:
            raise ConfigError("\n".join(problems))


def parsed_command_line(arguments: Sequence[str]) -> tuple[Any, list[Any]] | None:
    """``(Hydra's parsed arguments, the overrides)`` of a command line as ``@hydra.main`` reads it;
    ``None`` for a command line that runs nothing (``--help``, ``--info``, ...) or whose overrides
    Hydra cannot parse (its message says where)."""
    from hydra._internal.utils import get_args_parser  # what @hydra.main parses the command line with
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parsed = get_args_parser().parse_args(list(arguments))
    if parsed.help or parsed.hydra_help or parsed.info or parsed.shell_completion or parsed.experimental_rerun:
        return None
    try:
        return parsed, OverridesParser.create().parse_overrides(parsed.overrides)
    except HydraException:
        return None


def override_values(override: Any) -> list[str]:
    """The option names ``override`` sets, as text: one, or each of a choice or range sweep; none for
    a glob or interval sweep, a deletion, ``null`` or a mapping or list (a node's value, as
    ``logger={}`` empties a group's node: no option of it)."""
    if override.is_delete():
        return []
    if override.is_sweep_override():
        if override.is_range_sweep() or override.value_type.name in ("SIMPLE_CHOICE_SWEEP", "CHOICE_SWEEP"):
            return [str(value) for value in override.sweep_string_iterator()]
        return []
    value = override.value()
    return [] if value is None or isinstance(value, (dict, list)) else [str(value)]


def group_override_problems(config_dir: Path, config_name: str, arguments: Sequence[str]) -> list[str]:
    """The errors of the overrides in ``arguments`` that choose an option of a config group (a
    folder of ``config_dir`` or of the command line's ``--config-dir``): a group the command's
    primary config ``config_name`` does not choose (`defaults_groups`; Hydra's advice, ``+group=``,
    would add it to a command that does not use it), or an option no folder of the group holds,
    named with the nearest (`unknown_option_message`). Hydra's own groups (``hydra/...``) are Hydra's."""
    found = parsed_command_line(arguments)
    if found is None:
        return []
    parsed, overrides = found
    folders = [Path(parsed.config_dir).resolve(), config_dir] if parsed.config_dir else [config_dir]
    folders += searchpath_folders(overrides)
    name = parsed.config_name or config_name
    groups = defaults_groups(next((f / f"{name}.yaml" for f in folders if (f / f"{name}.yaml").is_file()), None))
    problems = []
    for override in overrides:
        group = override.key_or_group
        options = sorted({path.stem for folder in folders for path in (folder / group).glob("*.yaml")})
        if override.is_hydra_override() or override.is_delete() or not options:
            continue  # not a config group: a key (`unknown_override_keys`)
        adds = override.is_add() or override.is_force_add()
        if groups is not None and not adds and group.split("/")[0] not in groups:
            problems.append(missing_group_message(config_dir, name, group, groups, override.input_line))
            continue
        problems += [
            unknown_option_message(group, value, options, override.input_line)
            for value in override_values(override)
            if value not in options
        ]
    return problems


def searchpath_folders(overrides: Sequence[Any]) -> list[Path]:
    """The folders a command line's ``hydra.searchpath=[file://DIR, ...]`` adds to Hydra's config
    search path (``pkg://`` entries name packages: their options are not looked up)."""
    folders = []
    for override in overrides:
        if override.key_or_group == "hydra.searchpath" and not override.is_sweep_override():
            value = override.value()
            entries = value if isinstance(value, list) else [value]
            folders += [Path(str(e).removeprefix("file://")) for e in entries if str(e).startswith("file://")]
    return folders


def defaults_groups(primary: Path | None) -> set[str] | None:
    """The top-level config groups the defaults list of the primary config file ``primary`` chooses
    (``model`` for ``model: densevlad``, ``model@validation_references.x: ...``, ``optional model: ...``),
    Hydra's own left out; ``None`` when there is no such file (a config of the user's, not found)."""
    if primary is None:
        return None
    groups = set()
    for entry in OmegaConf.load(primary).get("defaults", []):
        if isinstance(entry, str) or len(entry) != 1:
            continue  # _self_, or a config of the same group
        key = str(next(iter(entry))).removeprefix("override ").removeprefix("optional ").lstrip("/")
        group = key.split("@", 1)[0].split("/", 1)[0]
        if group != "hydra":
            groups.add(group)
    return groups


def missing_group_message(config_dir: Path, name: str, group: str, groups: set[str], line: str) -> str:
    """The error of an override of ``group``, which the command ``name`` does not choose: the other
    commands whose primary configs (in ``config_dir``) do, and the command's own groups."""
    others = sorted(
        path.stem
        for path in config_dir.glob("*.yaml")
        if path.stem != name and group.split("/")[0] in (defaults_groups(path) or ())
    )
    where = f"; it is {' and '.join(others)}'s (locretrieval {others[0]} {line})" if others else ""
    return f"{group}: {name} has no config group {group}{where}; {name}'s groups: {', '.join(sorted(groups))}"


def unknown_option_message(group: str, value: str, options: Sequence[str], line: str) -> str:
    """The error of ``group=value`` where the group holds no option ``value``: the nearest options
    and every option, on one line (Hydra's lists them one a line, with its search path)."""
    near = difflib.get_close_matches(value, options, n=2, cutoff=0.6)
    suggestion = f"; did you mean {' or '.join(near)}?" if near else ""
    return f"{group}={value}: no such option of {group}{suggestion} (its options: {', '.join(options)})" + (
        f" (the command line's {line})" if line != f"{group}={value}" else ""
    )


#: The values ``device`` takes (configs/evaluate.yaml): ``auto`` picks a GPU when there is one.
DEVICES = re.compile(r"auto|cpu|cuda(:\d+)?")


def device_problems(arguments: Sequence[str]) -> list[str]:
    """The errors of the command line's ``device=`` values that are no device (``gpu``): named as
    typed, with the choices; otherwise the value is refused where it lands (``sfm.matching.device``)."""
    found = parsed_command_line(arguments)
    overrides = [] if found is None else found[1]
    return [
        f"device={value}: no such device; choose auto (a GPU when there is one), cpu, cuda or cuda:N"
        for override in overrides
        if override.key_or_group == "device" and not override.is_hydra_override()
        for value in override_values(override)
        if not DEVICES.fullmatch(value)
    ]


def unknown_override_keys(config_dir: Path, config_name: str, arguments: Sequence[str]) -> list[str]:
    """The errors of the overrides in ``arguments`` (a command line as Hydra's parser reads it) that
    set a key the config, composed with the other overrides, lacks (`unknown_override_message`);
    a sweep counts with its first value, an ``interval`` or glob sweep not at all. Whatever else
    Hydra would refuse is left to Hydra's message.

    Composing costs about half a second of CPU, which every run would pay: the config is composed
    only when an override sets a value (`sets_a_value`: not a group's option) of a key that is
    surely absent (`plausible_key`: a typo, a parameter no YAML sets). A key whose parts are all
    elsewhere in the configs but not in this composition (``module.loss.bins`` without ``loss=ap``)
    is left to Hydra's refusal."""
    from hydra._internal.utils import get_args_parser  # what @hydra.main parses the command line with
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parsed = get_args_parser().parse_args(list(arguments))
    if parsed.help or parsed.hydra_help or parsed.info or parsed.shell_completion or parsed.experimental_rerun:
        return []
    if parsed.config_path or parsed.config_dir:  # configs this check does not see
        return []
    try:
        overrides = OverridesParser.create().parse_overrides(parsed.overrides)
    except HydraException:  # a syntax error: Hydra's message says where
        return []
    top_level, words = config_names(config_dir, parsed.config_name or config_name)
    if not any(
        sets_a_value(override, config_dir) and not plausible_key(override.key_or_group, top_level, words)
        for override in overrides
    ):
        return []
    composable = [line for override in overrides if (line := composable_override(override)) is not None]
    refused: dict[str, str] = {}  # key -> the override that set it
    while True:
        attempt = [line for line in composable if line not in refused.values()]
        try:
            config = composed(config_dir, parsed.config_name or config_name, attempt)
        except HydraException as error:
            key = refused_key(error)
            line = next((line for line in attempt if key is not None and override_key(line) == key), None)
            if line is None:  # another refusal (a group's option that does not exist, ...): Hydra's to report
                return []
            refused[key] = line
            continue
        name = parsed.config_name or config_name
        return [
            unknown_override_message(config, key, line) + elsewhere(config_dir, name, key)
            for key, line in refused.items()
        ]


def config_names(config_dir: Path, config_name: str) -> tuple[set[str], set[str]]:
    """``(top-level keys, words)`` of the configs in ``config_dir``: the config groups, and the
    unindented keys and packages (``model@validation_references.x``) of the primary config
    ``config_name`` and of the ``@package _global_`` files; every word of the files' text (keys,
    packages, values) and the names of files and folders. About 20 ms for 120 files."""
    top_level = {path.name for path in config_dir.iterdir() if path.is_dir()}
    words = set()
    for path in config_dir.rglob("*"):
        words.add(path.stem)
        if path.suffix == ".yaml":
            text = path.read_text()
            words.update(re.findall(r"[A-Za-z_][\w-]*", text))
            if path == config_dir / f"{config_name}.yaml" or re.search(r"^# @package _global_", text, re.M):
                top_level.update(re.findall(r"^([A-Za-z_][\w-]*):", text, re.M))
                top_level.update(re.findall(r"\w@([A-Za-z_][\w-]*)", text))
    return top_level, words


def plausible_key(key: str, top_level: set[str], words: set[str]) -> bool:
    """Whether ``key`` (``a.b.c``) may be in the composed config: its first part a top-level key
    and every other part a word of the configs (`config_names`); one that is not is surely absent."""
    first, *rest = key.split(".")
    return first in top_level and set(rest) <= words


def composable_override(override: Any) -> str | None:
    """``override`` (Hydra's `Override`) as composing the config once takes it: a sweep by its
    first value, an ``interval`` or glob sweep and Hydra's own keys (``hydra.``, ``hydra/``) not at
    all (``None``)."""
    if override.is_hydra_override():
        return None
    if not override.is_sweep_override():
        return override.input_line
    if not (override.is_range_sweep() or override.value_type.name in ("SIMPLE_CHOICE_SWEEP", "CHOICE_SWEEP")):
        return None
    return f"{override.get_key_element()}={next(override.sweep_string_iterator())}"


def sets_a_value(override: Any, config_dir: Path) -> bool:
    """Whether ``override`` changes a key the config must have: not an addition or deletion
    (``+``, ``++``, ``~``), not Hydra's, not a config group's option (a folder of ``config_dir``)."""
    return not (
        override.is_add()
        or override.is_force_add()
        or override.is_delete()
        or override.is_hydra_override()
        or (config_dir / override.key_or_group.replace(".", "/")).is_dir()
    )


def composed(config_dir: Path, config_name: str, overrides: list[str]) -> DictConfig:
    """The config ``config_name`` of ``config_dir`` composed with ``overrides`` (Hydra's compose API)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(config_dir.resolve()), version_base="1.3"):
        return compose(config_name, overrides=overrides)


def override_key(line: str) -> str:
    """The key of an override line (``a.b=1`` -> ``a.b``)."""
    return line.split("=", 1)[0].lstrip("+~")


def refused_key(error: Exception) -> str | None:
    """The key of the override Hydra refused as absent from the config, or ``None`` for any other
    refusal."""
    found = re.match(r"Could not override '([^']+)'", str(error))
    return found.group(1) if found else None


def unknown_override_message(config: DictConfig, key: str, line: str) -> str:
    """The error of the override ``line`` of ``key``, absent from ``config``: the first part of
    ``key`` the config lacks (`unknown_key`: the keys beside it, the nearest), else, when none is
    near, the config's keys whose last part is near (``max_epochs`` -> ``trainer.max_epochs``), and
    how to add a key its YAML does not set (a parameter of the node's ``_target_``)."""
    parts = key.split(".")
    node = OmegaConf.to_container(config, resolve=False)
    depth = 0
    while depth < len(parts) - 1 and isinstance(node.get(parts[depth]), dict):
        node, depth = node[parts[depth]], depth + 1
    keys = [str(name) for name in node]
    message = unknown_key(".".join(parts[: depth + 1]), keys)
    if not difflib.get_close_matches(parts[depth], keys):
        elsewhere = nearest_keys(config, parts[-1])
        if elsewhere:
            message += f"; did you mean {' or '.join(elsewhere)}?"
        if "_target_" in node and depth == len(parts) - 1:
            message += f"; a parameter of {node['_target_']} that the config does not set is added with +{line}"
    return f"{message} (the command line's {line})"


#: What a user of another tool may type for a command, and what the command has instead.
SYNONYMS = {
    ("train", "dry_run"): "debug=quick (a few batches of a small scene, under a minute)",
    ("train", "fast_dev_run"): "debug=quick (a few batches of a small scene, under a minute)",
}


def elsewhere(config_dir: Path, name: str, key: str) -> str:
    """A hint for a ``key`` the command ``name`` lacks: what it has instead (`SYNONYMS`), and the
    other commands whose primary configs (in ``config_dir``) have the key's top-level key."""
    top = key.split(".", 1)[0]
    hint = f"; instead, {SYNONYMS[name, top]}" if (name, top) in SYNONYMS else ""
    others = [
        path.stem for path in sorted(config_dir.glob("*.yaml")) if path.stem != name and top in OmegaConf.load(path)
    ]
    if others:
        hint += f"; {top} is a key of {' and '.join(others)} (locretrieval {others[0]} {top}=...)"
    return hint


def nearest_keys(config: DictConfig, name: str) -> list[str]:
    """The full keys of ``config`` whose last part is near ``name`` (difflib's close matches, a
    stricter cutoff than for the keys beside it; at most 3)."""
    full_keys: dict[str, list[str]] = {}

    def walk(node: Any, prefix: str) -> None:
        for child, value in node.items():
            full_key = f"{prefix}{child}"
            full_keys.setdefault(str(child), []).append(full_key)
            if isinstance(value, dict):
                walk(value, f"{full_key}.")

    walk(OmegaConf.to_container(config, resolve=False), "")
    near = difflib.get_close_matches(name, list(full_keys), cutoff=0.75)
    return [full_key for last in near for full_key in full_keys[last]][:3]


def composed_training_scenes(cfg: DictConfig) -> list[DictConfig]:
    """The data nodes of the scenes a train.py config's ``training.scenes`` names (a data config's name,
    or ``{config: <name>, ...}``), each composed by Hydra as ``data=<name>`` composes it (its defaults
    list applied, its interpolations left for the run's config), in the list's order: the entry point
    composes them, the build step makes their scenes (`locretrieval.build.build_training`)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    names = [entry if isinstance(entry, str) else entry.get("config") for entry in cfg.training.scenes]
    known = {path.stem for path in (configs_dir() / "data").glob("*.yaml")}
    unknown = [name for name in names if name not in known]
    if unknown:
        raise ConfigError(f"training.scenes: no data config {unknown[0]!r}; expected one of {sorted(known)}")
    if GlobalHydra.instance().is_initialized():  # in train.py's Hydra app
        return [compose(config_name="train", overrides=[f"data={name}"]).data for name in names]
    with initialize_config_dir(config_dir=str(configs_dir()), version_base="1.3"):
        return [compose(config_name="train", overrides=[f"data={name}"]).data for name in names]
