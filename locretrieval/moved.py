"""Module paths that moved keep working: `locretrieval.models` grouped its modules and
``locretrieval.localization`` was split into `locretrieval.paradigms` and `locretrieval.sfm` (0.12);
the reports of training runs moved from `locretrieval.training` into `locretrieval.report`; the
forecast of a dry run from `locretrieval.sfm` into `locretrieval.paradigms`.

Saved run configs (``config.yaml``, ``.hydra/config.yaml``), checkpoints' architectures and code of
other packages name modules such as ``locretrieval.models.netvlad`` or classes such as
``locretrieval.models.heads.MixVPRHead``; a saved run's ``sfm`` section names
``locretrieval.localization.features.SiftFeatures``. `MovedModuleFinder`, on ``sys.meta_path`` from
the moment `locretrieval` is imported, answers each old name of `MOVED_MODULES` with the module
at its new path itself (one module object under two names, never a copy): ``import``,
``hydra.utils.get_class``, Hydra's ``_target_`` and pickle's class references all resolve through
it, with a `DeprecationWarning` naming the new path. A path recorded as data, such as the
``_target_`` of a checkpoint's architecture, is read under its new name by `current_path`.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import warnings
from types import ModuleType
from typing import Any

#: Modules that moved: the old dotted name -> the new (0.12: models, localization; then training's reports).
#: ``models.published``: the descriptors of the paper's benchmark with their authors' weights
#: (DenseVLAD and its parts, NetVLAD, AP-GeM, DELG); ``models.trainable``: the networks train.py
#: trains (trunks, heads, DINOv2); ``models.files``: weight files and descriptor feature files.
#: ``localization``: the paradigms (and their base, once ``paradigm``) to `locretrieval.paradigms`, the
#: SfM pipeline's modules to `locretrieval.sfm` (``sfm`` is now ``sfm.inputs``), ``estimates`` up.
#: ``training``'s reports to `locretrieval.report`: the training report (``training.report``), the
#: summary of runs and sweeps (``training.summary``) and the reader of their folders (``training.folders``).
#: ``sfm.forecast``: the dry run's forecast of the SfM paradigms' work, beside the paradigms it runs.
MOVED_MODULES = {
    **{
        f"locretrieval.models.{name}": f"locretrieval.models.{group}.{name}"
        for group, names in {
            "published": "densevlad dense_sift densevlad_kernels vlad netvlad apgem delg",
            "trainable": "backbones timm_trunk efficientnet heads dinov2",
            "files": "weights feature_io precomputed",
        }.items()
        for name in names.split()
    },
    "locretrieval.localization": "locretrieval.paradigms",
    **{
        f"locretrieval.localization.{old}": f"locretrieval.{new}"
        for old, new in {
            "approximation": "paradigms.approximation",
            "local_sfm": "paradigms.local_sfm",
            "global_sfm": "paradigms.global_sfm",
            "paradigm": "paradigms.base",
            "estimates": "estimates",
            "sfm": "sfm.inputs",
            "plan": "sfm.work",  # the work counted (its forecast is gone: a dry run's, paradigms.forecast)
            "workers": "pool",
            **{
                name: f"sfm.{name}"
                for name in (
                    "colmap_model features matching nearest_neighbours pairs pipeline pnp pose_cache "
                    "sparse_map store triangulation verification"
                ).split()
            },
        }.items()
    },
    "locretrieval.training.report": "locretrieval.report.training",
    "locretrieval.training.summary": "locretrieval.report.training_summary",
    "locretrieval.training.folders": "locretrieval.report.training_runs",
    "locretrieval.sfm.forecast": "locretrieval.paradigms.forecast",
}


def current_path(path: str) -> str:
    """``path`` (a module, or a name in one: ``module.Class``) with a module of `MOVED_MODULES` at its
    new name; any other path unchanged."""
    for old, new in MOVED_MODULES.items():
        if path == old or path.startswith(f"{old}."):
            return new + path[len(old) :]
    return path


def current_targets(settings: Any) -> Any:
    """``settings`` (plain JSON types, e.g. a checkpoint's architecture) with every ``_target_``
    string at its `current_path`, at any depth."""
    if isinstance(settings, dict):
        return {
            key: current_path(value) if key == "_target_" and isinstance(value, str) else current_targets(value)
            for key, value in settings.items()
        }
    if isinstance(settings, list):
        return [current_targets(value) for value in settings]
    return settings


class MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds a module of `MOVED_MODULES` by its old name and loads it as the module of its new name:
    the placeholder the import system makes is replaced in ``sys.modules`` by that module, which
    the import then returns (and binds as the old name's attribute of its package)."""

    def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> importlib.machinery.ModuleSpec | None:
        if fullname not in MOVED_MODULES:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> None:
        return None  # the import system's empty placeholder, replaced in exec_module

    def exec_module(self, module: ModuleType) -> None:
        new = MOVED_MODULES[module.__name__]
        warnings.warn(f"{module.__name__} is now {new}", DeprecationWarning, stacklevel=2)
        sys.modules[module.__name__] = importlib.import_module(new)


def install() -> None:
    """Put one `MovedModuleFinder` first on ``sys.meta_path`` (it answers only the old names)."""
    if not any(isinstance(finder, MovedModuleFinder) for finder in sys.meta_path):
        sys.meta_path.insert(0, MovedModuleFinder())
