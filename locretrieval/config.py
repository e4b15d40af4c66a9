"""Configuration: the OmegaConf resolvers of ``configs/`` and the one validation layer of its sections.

Defaults live in one place, the YAML files of ``configs/``. Each section the code reads has
a dataclass schema without defaults, next to the code that reads it. `validated` checks a
section against its schema the same way everywhere: an unknown key, a missing key or a value
of the wrong type is a `ConfigError` naming the full key (``paradigms.approximation.k[0]``)
and what was expected; each schema's ``__post_init__`` checks ranges with `require`, whose
error `validated` prefixes with the section's key.
"""

from __future__ import annotations

import collections.abc
import dataclasses
import difflib
import hashlib
import inspect
import os
import re
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

from omegaconf import Container, DictConfig, OmegaConf
from omegaconf.errors import ConfigKeyError, MissingMandatoryValue, OmegaConfBaseException

from locretrieval import parts
from locretrieval.cache import safe_name
from locretrieval.errors import ConfigError, DataFileError, SettingError, require  # noqa: F401  (imported from here)

Schema = TypeVar("Schema")


def folder_label(folders: Sequence[str | os.PathLike]) -> str:
    """The feature names of ``folders``, distinct ones joined by ``+``: their last component
    (``.../reconstruction/global_features/AP-GeM-LM18`` -> ``AP-GeM-LM18``), the one before in
    the downloader's layout (``.../global_features/AP-GeM-LM18/global_features`` -> ``AP-GeM-LM18``),
    an hloc file's name without its suffix (``global-feats-netvlad.h5`` -> ``global-feats-netvlad``)."""

    def label(folder: Path) -> str:
        if folder.suffix.lower() in (".h5", ".hdf5"):  # an hloc features file: its name without the suffix
            return folder.stem
        return (
            folder.parent.name
            if folder.name == "global_features" and folder.parent.parent.name == "global_features"
            else folder.name
        )

    return "+".join(dict.fromkeys(label(Path(folder)) for folder in folders))


def precomputed_name(path: Any, feature_name: str | None) -> str:
    """``${precomputed_name:${model.path},${model.feature_name}}``, the ranking name of precomputed
    features: the `folder_label` of ``path`` (a folder or a list), else ``feature_name``, else
    ``precomputed`` (the one feature type of the scene's sources is found only once it loads)."""
    if path is not None:
        return folder_label([path] if isinstance(path, (str, os.PathLike)) else list(path))
    return feature_name or "precomputed"


if not OmegaConf.has_resolver("precomputed_name"):
    OmegaConf.register_new_resolver("precomputed_name", precomputed_name)


def file_stem(path: Any) -> str:
    """``${file_stem:${model.path}}``: a file's name without its extension (a ranking name)."""
    return Path(str(path)).stem


if not OmegaConf.has_resolver("file_stem"):
    OmegaConf.register_new_resolver("file_stem", file_stem)


#: Characters longer sweep folder names lose (kept: the job number, the overrides' start, a hash).
JOB_DIRNAME_LENGTH = 96


def job_dirname(number: Any, label: Any) -> str:
    """``${job_dirname:${hydra.job.num},${hydra.job.override_dirname}}``: a multirun job's folder
    name, ``<number>_<label>`` with each override's key shortened to its last part
    (``sampler.anchors=3`` -> ``anchors=3``), a value with 4 decimals or more rounded
    to 3 (an Optuna trial's ``blur_probability=0.489309171116382`` -> ``blur_probability=0.489``)
    and every character but letters, digits and ``._=,+-`` made ``-``; a longer one is cut to
    `JOB_DIRNAME_LENGTH` characters ending in a hash of the whole label (so it stays unique). The
    job's full overrides are in its ``.hydra/overrides.yaml``."""
    short = re.sub(r"(^|,)[~+]*(?:[\w@/-]+\.)+(?=[\w-]+=)", r"\1", str(label))
    short = re.sub(r"(?<==)-?\d+\.\d{4,}(?:e-?\d+)?(?=,|$)", lambda number: f"{float(number.group()):.3g}", short)
    name = f"{number}_{re.sub(r'[^A-Za-z0-9._=,+-]', '-', short)}".rstrip(".")
    if len(name) <= JOB_DIRNAME_LENGTH:
        return name
    digest = hashlib.sha256(str(label).encode()).hexdigest()[:12]
    return f"{name[: JOB_DIRNAME_LENGTH - len(digest) - 1]}-{digest}"


if not OmegaConf.has_resolver("job_dirname"):
    OmegaConf.register_new_resolver("job_dirname", job_dirname)


def job_label(number: Any) -> str:
    """``${job_label:${oc.select:hydra.job.num,null}}``: ``[job <number>]`` for a job of a multirun
    (the console's log lines, configs/hydra/job_logging/), nothing for a single run (``None``)."""
    return "" if number is None else f"[job {number}]"


if not OmegaConf.has_resolver("job_label"):
    OmegaConf.register_new_resolver("job_label", job_label)


if not OmegaConf.has_resolver("safe_name"):
    # ``${safe_name:${model.name}}``: a name from the config as one folder name of Hydra's run folder
    OmegaConf.register_new_resolver("safe_name", safe_name)


def trainer_accelerator(device: str) -> str:
    """``${trainer_accelerator:${device}}``: Lightning's accelerator for the run's ``device``
    (``auto``: ``gpu`` when torch sees a CUDA GPU, else ``cpu``)."""
    from locretrieval.device import resolve_device

    return "gpu" if resolve_device(str(device)).type == "cuda" else "cpu"


def trainer_precision(device: str) -> str:
    """``${trainer_precision:${device}}``: mixed float16 on a GPU, float32 on a CPU."""
    return "16-mixed" if trainer_accelerator(device) == "gpu" else "32-true"


for _name, _resolver in (("trainer_accelerator", trainer_accelerator), ("trainer_precision", trainer_precision)):
    if not OmegaConf.has_resolver(_name):
        OmegaConf.register_new_resolver(_name, _resolver)


#: Keys that moved (0.12) when their value became an object chosen by ``_target_``, a part of the
#: training module (the loss, optimizer, scheduler and memory nest under ``module``) or a key of the
#: job (``shard``): the old key -> its new spelling. An override of an old key is refused naming the
#: new one, on the command line (`refuse_moved_keys`) and where a section is checked (an unknown
#: key, `validated`).
MOVED_KEYS = {
    "training.frozen": "module.frozen",
    "training.freeze_batch_norm": "module.freeze_batch_norm",
    "train_relevance.unrelated_rotation": "train_relevance.negatives.max_rotation",
    "train_relevance.far": "train_relevance.negatives.far",
    "paradigms.approximation.alpha": "paradigms.approximation.weights.csi.alpha",
    "sfm.matching.max_epipolar_error": "sfm.database_verification.max_epipolar_error",
    "train_relevance.negatives.rule": "train_relevance/negatives=unrelated|not_relevant",
    "subsets.mask_source": "subsets.dynamic_masks, the names of subsets.mask_sources tried in order "
    "(auto: [masks,maskrcnn], masks: [masks], maskrcnn: [maskrcnn], none: [])",
    "data.ltvl_name_style": "data/ltvl_names=full|basename|strip_prefix",
    "sfm.shard": "shard, a key of the job: python evaluate.py -m 'shard=0/4,1/4,2/4,3/4'",
    **{
        f"subsets.maskrcnn_{key}": f"subsets.mask_sources.maskrcnn.{key}"
        for key in ("weights", "min_size", "score_threshold", "mask_threshold")
    },
    # the training config nests as its objects do: the loss, optimizer and scheduler of the module
    **{
        f"{part}.{key}": f"module.{part}.{key}"
        for part, keys in {
            "loss": "temperature target_temperature bins margin max_triplets_per_anchor pos_margin neg_margin "
            "loss loss.alpha loss.beta loss.base",
            "optimizer": "lr weight_decay",
            "scheduler": "T_max",
        }.items()
        for key in keys.split()
    },
    "module.memory_size": "memory=cross_batch module.memory.size",
}


def unknown_key(full_key: str, known: Sequence[str]) -> str:
    """The error of an unknown ``full_key``: the keys ``known`` there and the nearest of them
    (difflib's close matches of its last part); a moved key's new spelling."""
    if full_key in MOVED_KEYS:
        return f"{full_key}: moved, now {MOVED_KEYS[full_key]}"
    near = difflib.get_close_matches(full_key.rsplit(".", 1)[-1], [str(key) for key in known])
    return f"{full_key}: unknown key; expected one of {list(known)}" + (
        f"; did you mean {' or '.join(near)}?" if near else ""
    )


def refuse_moved_keys(overrides: Sequence[str]) -> None:
    """Raise `ConfigError` for a command-line override (``key=value``, ``+key=value``, ``~key``) of a
    key in `MOVED_KEYS`, naming the new spelling: Hydra would refuse it as a key the config lacks."""
    for override in overrides:
        key = override.lstrip("+~").split("=", 1)[0]
        if key in MOVED_KEYS:
            raise ConfigError(unknown_key(key, []) + f" (the command line's {override})")


def validated(schema: type[Schema], config: Any, key: str) -> Schema:
    """``config`` (a `DictConfig`, a mapping or already a ``schema`` instance) as a checked ``schema``.

    Interpolations are resolved against the config's own root first. Nested dataclass fields
    are built recursively, so every error names the full key below ``key``. A schema with a
    ``from_mapping(mapping, key)`` builds itself (sections known only from a registry, e.g. the
    paradigms).
    """
    if isinstance(config, schema):
        return config
    if hasattr(schema, "from_mapping"):
        mapping = OmegaConf.to_container(config, resolve=True) if isinstance(config, Container) else dict(config or {})
        return schema.from_mapping(mapping, key)
    try:
        if isinstance(config, Container):
            config = OmegaConf.to_container(config, resolve=True)
        node = OmegaConf.merge(OmegaConf.structured(schema), config if config is not None else {})
    except OmegaConfBaseException as error:
        raise ConfigError(_message(schema, key, error)) from None
    return _build(schema, node, key)


def validated_sections(cfg: Any, schemas: Mapping[str, type]) -> dict[str, Any]:
    """Every section ``key`` of ``cfg`` checked against its ``schemas[key]`` (`validated`), by key."""
    return {key: validated(schema, OmegaConf.select(cfg, key), key) for key, schema in schemas.items()}


def part(kind: type, group: str | None = None) -> Any:
    """A schema field holding an object chosen by ``_target_`` (``query_verification: Any =
    part(PairVerification, "sfm/query_verification")``): `validated` checks its node's keys against
    the target's parameters (`check_node`), builds it and requires an instance of ``kind``.
    ``group``: the config group whose options choose it, named when a plain name is given instead."""
    return dataclasses.field(metadata={"part": kind, "group": group})


def named_parts(kind: type) -> Any:
    """A schema field holding a mapping of names to objects chosen by ``_target_`` (``weights:
    dict[str, Any] = named_parts(ApproximationMethod)``), each checked and built as a `part`."""
    return dataclasses.field(metadata={"parts": kind})


def require_part(value: Any, kind: type, key: str, group: str | None = None) -> Any:
    """``value`` if it is a ``kind`` (an object its config node's ``_target_`` built), else a
    `ConfigError` naming ``key``; a plain name says which option of ``group`` chooses it now."""
    if isinstance(value, kind):
        return value
    if isinstance(value, str) and group is not None:
        raise ConfigError(
            f"{key}: a {kind.__name__} is chosen by its config group now: {group}={value} "
            f"(configs/{group}/{value}.yaml), not {key}={value}"
        )
    raise ConfigError(f"{key}: expected a node with a _target_ (a {kind.__name__}), got {value!r}")


def build_part(kind: type, node: Any, where: str, group: str | None = None) -> Any:
    """The ``kind`` the config node ``node`` at ``where`` builds (its ``_target_``, its keys checked
    by `check_node`), or ``node`` if it is a ``kind`` already; a `ConfigError` naming the key
    otherwise (a plain name: the ``group`` option that chooses it now, `require_part`)."""
    if isinstance(node, collections.abc.Mapping) and not isinstance(node, Container):
        node = OmegaConf.create(dict(node))
    if not isinstance(node, Container) or "_target_" not in node:
        return require_part(node, kind, where, group)  # refused unless already built
    check_node(node, where, kind)
    built_part = built(node, where)
    if not isinstance(built_part, kind):
        raise ConfigError(f"{where}._target_: {node['_target_']} does not build a {kind.__name__}")
    return built_part


def _build(schema: type[Schema], node: DictConfig, key: str) -> Schema:
    hints = typing.get_type_hints(schema)
    values = {}
    for field in dataclasses.fields(schema):
        where = f"{key}.{field.name}"
        try:
            value = node[field.name]
        except MissingMandatoryValue:
            raise ConfigError(f"{where}: missing; expected {_type_name(hints[field.name])}") from None
        item = _dataclass_items(hints[field.name])
        if "part" in field.metadata:
            values[field.name] = build_part(field.metadata["part"], value, where, field.metadata["group"])
        elif "parts" in field.metadata:
            values[field.name] = {
                name: build_part(field.metadata["parts"], entry, f"{where}.{name}") for name, entry in value.items()
            }
        elif item is not None:
            values[field.name] = [_build(item, entry, f"{where}[{index}]") for index, entry in enumerate(value)]
        elif dataclasses.is_dataclass(hints[field.name]):
            values[field.name] = _build(hints[field.name], value, where)
        else:
            values[field.name] = OmegaConf.to_container(value) if isinstance(value, Container) else value
    try:
        return schema(**values)
    except SettingError as error:
        raise ConfigError(f"{key}.{error}") from None


def _dataclass_items(hint: Any) -> type | None:
    """``X`` when ``hint`` is a list of dataclass ``X`` (each built and checked), else None."""
    arguments = typing.get_args(hint)
    if (
        typing.get_origin(hint) in (list, Sequence, collections.abc.Sequence)
        and len(arguments) == 1
        and dataclasses.is_dataclass(arguments[0])
    ):
        return arguments[0]
    return None


def _message(schema: type, key: str, error: OmegaConfBaseException) -> str:
    path = str(getattr(error, "full_key", "") or "")
    full_key = ".".join(part for part in (key, path) if part)
    if isinstance(error, ConfigKeyError) and dataclasses.is_dataclass(getattr(error, "object_type", None)):
        return unknown_key(full_key, [field.name for field in dataclasses.fields(error.object_type)])
    expected = _hint_at(schema, path)
    return f"{full_key}: {str(error).splitlines()[0]}" + (f"; expected {_type_name(expected)}" if expected else "")


def _hint_at(schema: type, path: str) -> Any:
    """The type hint of the field at ``path`` (``a.b[0]``) of ``schema``, or ``None``."""
    hint: Any = schema
    for part in re.findall(r"\[\d+\]|[^.\[\]]+", path):
        if part.startswith("["):
            arguments = typing.get_args(hint)
            hint = arguments[0] if arguments else None
        elif dataclasses.is_dataclass(hint):
            hint = typing.get_type_hints(hint).get(part)
        else:
            return None
        if hint is None:
            return None
    return hint


def _type_name(hint: Any) -> str:
    if dataclasses.is_dataclass(hint):
        return f"a section with keys {[field.name for field in dataclasses.fields(hint)]}"
    if isinstance(hint, type):
        return hint.__name__
    return str(hint).replace("typing.", "")


#: Keys of a config node that are Hydra's, not its target's.
_HYDRA_NODE_KEYS = ("_target_", "_partial_", "_recursive_", "_convert_", "_args_")
#: Annotations OmegaConf checks and converts; any other parameter is checked as ``Any``.
_SIMPLE_TYPES = (int, float, bool, str)


def check_node(node: Any, key: str, kind: type | None = None) -> None:
    """Raise `ConfigError` naming the full key when the config node ``node`` (a ``_target_`` node)
    names what does not import or is not a ``kind`` (`locretrieval.parts.import_part`), has a key its
    target does not take, or a value its target's annotation refuses (int, float, bool, str, optional
    and list of them), as `validated` does for a schema: before any work."""

    target = parts.import_part(node["_target_"], key, parts.PartGroup((kind,)) if kind else parts.ANY_CALLABLE)
    values = {
        name: value
        for name, value in OmegaConf.to_container(node, resolve=True).items()
        if name not in _HYDRA_NODE_KEYS
    }
    parameters = inspect.signature(target).parameters
    if not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        unknown = [name for name in values if name not in parameters]
        if unknown:
            raise ConfigError(unknown_key(f"{key}.{unknown[0]}", list(parameters)))
    try:
        hints = typing.get_type_hints(target.__init__ if isinstance(target, type) else target)
    except Exception:  # annotations that do not resolve (a library's forward references): keys only
        hints = {}
    schema = dataclasses.make_dataclass(
        f"Node_{key.replace('.', '_')}", [(name, _checkable(hints.get(name, Any))) for name in values]
    )
    validated(schema, values, key)


def _checkable(hint: Any) -> Any:
    """``hint`` where OmegaConf can check it (simple types, optional, lists of them), else ``Any``."""
    if hint in _SIMPLE_TYPES:
        return hint
    arguments = [argument for argument in typing.get_args(hint) if argument is not type(None)]
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and len(arguments) == 1:
        inner = _checkable(arguments[0])
        return Any if inner is Any else typing.Optional[inner]
    if (
        typing.get_origin(hint) in (list, Sequence, collections.abc.Sequence)
        and len(arguments) == 1
        and arguments[0] in _SIMPLE_TYPES
    ):
        return typing.List[arguments[0]]
    return Any


def built(node: Any, key: str, **runtime: Any) -> Any:
    """The object of the config node ``node`` at ``key`` (its ``_target_``, Hydra's `instantiate`).
    A ``_partial_`` node is called with the ``runtime`` objects only the running code has (the
    scene, the training pairs, the network, ...); giving them to a node that is not partial is an
    error naming the key. A value its constructor refuses (a `SettingError` of a range check) is a
    `ConfigError` naming the full key; its own `ValueError` (a `ConfigError`, a `DataFileError`: a
    value or a file it refused) or `FileNotFoundError` (a weight file or dataset it reads) is raised as
    it is, not inside Hydra's one-line `InstantiationException`; a
    ``_target_`` that does not import is named by its key (`locretrieval.parts.import_part`)."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    if isinstance(node, Container) and "_target_" in node:
        parts.import_part(node["_target_"], key)
    if runtime and not node.get("_partial_", False):
        raise ConfigError(f"{key}: needs _partial_: true (the run gives it {sorted(runtime)})")
    try:
        target = instantiate(node, _convert_="all")  # plain lists and dicts: no config object past here
        return target(**runtime) if runtime else target
    except SettingError as error:
        raise ConfigError(f"{key}.{error}") from None
    except InstantiationException as error:
        if isinstance(error.__cause__, SettingError):
            raise ConfigError(f"{key}.{error.__cause__}") from None
        if isinstance(error.__cause__, (ValueError, FileNotFoundError)):
            raise error.__cause__ from None  # a part of it refused (naming its own key), or a file it reads
        raise
