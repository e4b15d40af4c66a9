"""Only parts can be called: every ``_target_`` of a config is checked before anything is imported or called.

A config names the objects a run builds by ``_target_`` (Hydra's `instantiate`, and the project's
own builders: `locretrieval.config.built`, backbones and poolings recorded in checkpoints, ground
truths, paradigms). A config is text anyone can share (a run's ``.hydra/config.yaml``), and Hydra
calls whatever it names: ``model.backbone._target_=subprocess.Popen`` ran a command, ``builtins.open``
with ``mode: w`` emptied a file. So a target must be a *part* of the group its key belongs to
(`PART_GROUPS`), checked by `resolve_part` in two steps:

1. before any import, its dotted path must lie in an allowed package: ``locretrieval``, the
   libraries the group's own options name (``torch.optim`` for ``module.optimizer``, ``lightning``
   for ``trainer``, ...) and the packages a user names in ``limits.trusted_packages``;
2. then the object must be a class defined in such a package (not one imported into it:
   ``locretrieval.config.os.system`` is refused) and a subclass of the group's base class where the
   group has one; a function counts where it is annotated to return that base (``data``'s loaders
   return a `locretrieval.scene.Scene`).

A key outside `PART_GROUPS` takes classes of the allowed packages only. `check_targets` checks every
``_target_`` below a config node (the entry points check the whole config before the run starts;
``hydra.*`` is Hydra's own, built before the run).
"""

from __future__ import annotations

import importlib
import inspect
import re
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from locretrieval import limits
from locretrieval.errors import ConfigError

#: The package whose classes are parts of every group.
OWN_PACKAGE = "locretrieval"
#: A dotted import path (``package.module.Name``).
DOTTED_PATH = re.compile(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*")


@dataclass(frozen=True)
class PartGroup:
    """The parts a config key takes: subclasses of ``bases`` (import paths; none: any class of an
    allowed package) from ``locretrieval``, ``packages`` (the libraries of the group's own options)
    and ``limits.trusted_packages``; with ``functions``, any function of those packages too."""

    bases: tuple[str, ...] = ()
    packages: tuple[str, ...] = ()
    functions: bool = False  # a function of an allowed package is a part too (a hook the code calls)


_CALLBACKS = PartGroup(("lightning.pytorch.callbacks.Callback",), ("lightning.pytorch.callbacks",))

#: Config keys (``*``: any one key or list index) whose ``_target_`` builds a part, and what a part there is.
PART_GROUPS: dict[str, PartGroup] = {
    "data": PartGroup(("locretrieval.scene.types.Scene",)),  # the loaders: functions returning a Scene
    "data.ltvl_names": PartGroup(("locretrieval.scene.ltvl.LtvlNames",)),
    "data.split": PartGroup(("locretrieval.scene.split.SceneSplit",)),
    "data.render.environments.*": PartGroup(("locretrieval.scene.synthetic.config.EnvironmentBuilder",)),
    "model": PartGroup(),  # anything with rankings(scene, search): a GlobalDescriptor, a pairs file, a user's model
    "validation_references.*": PartGroup(),
    "model.backbone": PartGroup(),  # a Backbone protocol: any class of an allowed package
    "model.pooling": PartGroup(("torch.nn.Module",)),
    "model.order": PartGroup(("locretrieval.retrieval.pairs_file.PairOrder",)),
    "groundtruth.definitions.*": PartGroup(),  # a Definition protocol (checked by its fields as well)
    "train_relevance.definition": PartGroup(),
    "groundtruth.relevance": PartGroup(("locretrieval.groundtruth.base.RelevanceScope",)),
    "train_relevance.negatives": PartGroup(("locretrieval.training.relevance.NegativesRule",)),
    "paradigms.*": PartGroup(("locretrieval.paradigms.base.Paradigm",)),
    "paradigms.approximation.weights.*": PartGroup(("locretrieval.paradigms.approximation.ApproximationMethod",)),
    "paradigms.local_sfm.map_matches": PartGroup(("locretrieval.paradigms.local_sfm.MapMatches",)),
    "sfm.features": PartGroup(("locretrieval.sfm.features.LocalFeatures",)),
    "sfm.query_verification": PartGroup(("locretrieval.sfm.verification.PairVerification",)),
    "sfm.database_verification": PartGroup(("locretrieval.sfm.verification.PairVerification",)),
    "sfm.triangulation": PartGroup(("locretrieval.sfm.triangulation.Triangulation",)),
    "subsets.mask_sources.*": PartGroup(("locretrieval.metrics.subsets.MaskSource",)),
    "augmentation": PartGroup(),
    "sampler": PartGroup(("torch.utils.data.Sampler",)),
    "datamodule": PartGroup(("lightning.pytorch.LightningDataModule",)),
    "module": PartGroup(("lightning.pytorch.LightningModule",)),
    "module.loss": PartGroup(("torch.nn.Module",)),
    "module.loss.loss": PartGroup(
        ("pytorch_metric_learning.losses.BaseMetricLossFunction",), ("pytorch_metric_learning.losses",)
    ),
    "module.loss.distance": PartGroup(
        ("pytorch_metric_learning.distances.BaseDistance",), ("pytorch_metric_learning.distances",)
    ),
    "module.loss.reducer": PartGroup(
        ("pytorch_metric_learning.reducers.BaseReducer",), ("pytorch_metric_learning.reducers",)
    ),
    "module.memory": PartGroup(("torch.nn.Module",)),
    "module.optimizer": PartGroup(("torch.optim.Optimizer",), ("torch.optim",)),
    "module.scheduler": PartGroup(("torch.optim.lr_scheduler.LRScheduler",), ("torch.optim.lr_scheduler",)),
    "miner": _CALLBACKS,
    "callbacks.*": _CALLBACKS,
    "logger.*": PartGroup(("lightning.pytorch.loggers.Logger",), ("lightning.pytorch.loggers",)),
    "trainer": PartGroup(("lightning.pytorch.Trainer",), ("lightning",)),
    "trainer.plugins.*": PartGroup(("lightning.fabric.plugins.CheckpointIO",), ("lightning",)),
    "hydra.sweeper.sampler": PartGroup(("optuna.samplers.BaseSampler",), ("optuna.samplers",)),
    "hydra.sweeper.custom_search_space": PartGroup(functions=True),  # (multirun config, trial) -> None
}


def pattern_of(key: str) -> str | None:
    """The `PART_GROUPS` pattern a config key (``groundtruth.definitions.frustum``, ``trainer.plugins[0]``)
    matches, or ``None``."""
    parts = [part for part in re.split(r"\.|\[|\]", key) if part]
    for pattern in PART_GROUPS:
        expected = pattern.split(".")
        if len(expected) == len(parts) and all(e in ("*", p) for e, p in zip(expected, parts)):
            return pattern
    return None


def group_of(key: str) -> PartGroup:
    """The `PartGroup` of a config key (`pattern_of`); a key outside `PART_GROUPS` takes any class of
    the allowed packages."""
    pattern = pattern_of(key)
    return PART_GROUPS[pattern] if pattern is not None else PartGroup()


def allowed_packages(group: PartGroup) -> tuple[str, ...]:
    """``locretrieval``, ``group``'s libraries and ``limits.trusted_packages``."""
    return (OWN_PACKAGE, *group.packages, *limits.current().trusted_packages)


def in_packages(path: str, packages: Sequence[str]) -> bool:
    """Whether the dotted ``path`` lies in one of ``packages`` (itself, or below it)."""
    return any(path == package or path.startswith(f"{package}.") for package in packages)


def resolve_part(target: Any, key: str, base: type | tuple[type, ...] | None = None) -> Any:
    """The class (or function returning a part) that ``target`` names at the config key ``key``, checked
    as the module docstring says, before importing anything outside the allowed packages or calling
    anything; ``base``: the class every part there is (instead of its group's). A `ConfigError`
    naming ``<key>._target_`` otherwise."""
    group = group_of(key)
    packages = allowed_packages(group)
    where = f"{key}._target_" if key else "_target_"
    if not isinstance(target, str) or not DOTTED_PATH.fullmatch(target):
        raise ConfigError(f"{where}: {target!r} is not an import path (package.module.Class)")
    if not in_packages(target, packages):
        raise ConfigError(
            f"{where}: {target} is not a part: a config may name classes of {list(packages)} only; a class of "
            "your own package is allowed once you name the package in limits.trusted_packages (nothing was imported)"
        )
    from hydra.utils import get_object

    try:
        found = get_object(target)
    except Exception as error:  # Hydra wraps the import error
        raise ConfigError(f"{where}: cannot import {target!r} ({error})") from None
    bases = base if isinstance(base, tuple) else (base,) if base is not None else _bases(group)
    hook = group.functions and inspect.isfunction(found) and in_packages(found.__module__, packages)
    problem = None if hook else _not_a_part(found, packages, bases)
    if problem:
        raise ConfigError(f"{where}: {target} is not a part of {key or 'the config'}: {problem}")
    return found


def _bases(group: PartGroup) -> tuple[type, ...]:
    bases = []
    for path in group.bases:
        module, _, name = path.rpartition(".")
        bases.append(getattr(importlib.import_module(module), name))
    return tuple(bases)


def _not_a_part(found: Any, packages: Sequence[str], bases: tuple[type, ...]) -> str | None:
    """Why ``found`` is not a part (``None``: it is)."""
    module = getattr(found, "__module__", None) or ""
    if not in_packages(module, packages):
        return f"it is defined in {module or 'no module'}, outside {list(packages)}"
    if inspect.isclass(found):
        if bases and not issubclass(found, bases):
            return f"a part there is a {' or '.join(b.__qualname__ for b in bases)}"
        return None
    if inspect.isfunction(found) and bases:
        try:
            returned = typing.get_type_hints(found).get("return")
        except Exception:  # annotations that do not resolve
            returned = None
        if isinstance(returned, type) and issubclass(returned, bases):
            return None
        return f"a function there must be annotated to return a {' or '.join(b.__qualname__ for b in bases)}"
    return "not a class"


def check_targets(node: Any, key: str = "") -> None:
    """`resolve_part` for every ``_target_`` in ``node`` (a config node or plain data) and below it, at
    its full key below ``key``; ``hydra`` at the top is left to Hydra. A node is checked as it
    resolves (an interpolation checked where it is used), or as written when it does not resolve."""
    if OmegaConf.is_config(node):
        try:
            node = OmegaConf.to_container(node, resolve=True)
        except OmegaConfBaseException:  # resolved when used (a ${hydra:...} outside a run): checked as written
            node = OmegaConf.to_container(node, resolve=False)
    _check_plain(node, key)


def _check_plain(node: Any, key: str) -> None:
    if isinstance(node, Mapping):
        for name, value in node.items():
            if name == "_target_":
                resolve_part(value, key)
            elif not (key == "" and name == "hydra"):
                _check_plain(value, f"{key}.{name}" if key else str(name))
    elif isinstance(node, (list, tuple)):
        for index, value in enumerate(node):
            _check_plain(value, f"{key}[{index}]")


def check_callable(target: str, key: str) -> None:
    """A ``package.module:function`` a config names to be called (``model=callable``'s ``model.target``): its
    module must lie in ``locretrieval`` or ``limits.trusted_packages``, checked before importing it."""
    module = target.partition(":")[0]
    packages = allowed_packages(PartGroup())
    if not DOTTED_PATH.fullmatch(module) or not in_packages(module, packages):
        raise ConfigError(
            f"{key}: {target!r} is not in {list(packages)}: name its package in limits.trusted_packages "
            "(e.g. limits.trusted_packages=[my_package]) to call it (nothing was imported)"
        )
