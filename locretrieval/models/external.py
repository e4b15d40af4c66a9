"""Descriptors from networks defined elsewhere: a torch.hub entry point or a researcher's callable.

Both give a module (or a function) mapping a normalised image batch ``float32 [B, 3, H, W]``
to global descriptors ``[B, D]`` (a tuple or list: its first element). `ModuleNet` makes it a
`RetrievalNet` (descriptors L2-normalised per scale), so it is described, cached and, for a
module with parameters, trained like the zoo's networks. Its preprocessing is config:
``max_side`` or a fixed ``size``, ``multiple_of`` (a ViT's patch size), ``mean``/``std``,
``scales``. The descriptor cache key holds the source (hub repo and entry, or the callable's
import path), the keyword arguments, the preprocessing and the state dict's hash.

Nothing is downloaded by locretrieval: ``model.source=github`` loads from torch.hub's own
cache (``torch.hub.get_dir()``), where the user's machine fetched the repository and weights;
without it the error names the repo and what to do.
"""

from __future__ import annotations

import importlib
import inspect
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from locretrieval.models.extraction import ExtractionSettings, Preprocessing
from locretrieval.models.files.weights import content_sha256, embedded_checkpoint, load_torch_file, plain
from locretrieval.models.networks import WeightsInfo, l2_normalize
from locretrieval.models.torch_descriptor import TorchGlobalDescriptor

HUB_SOURCES = ("local", "github")
#: ``(height, width)`` of the probe image that finds a network's output dimension.
PROBE_SIZE = (224, 224)


class ModuleNet(nn.Module):
    """A module or function ``images -> descriptors`` as a `RetrievalNet`: ``forward`` returns
    unit ``[B, D]`` descriptors (a tuple or list output: its first element, flattened);
    ``finalize`` is the identity; ``output_dim`` is found by running a probe image. An empty
    buffer marks the device of a module without parameters (not part of the state dict)."""

    def __init__(self, module: nn.Module | Callable[[torch.Tensor], Any], preprocessing: Preprocessing) -> None:
        super().__init__()
        self.module = module if isinstance(module, nn.Module) else _Function(module)
        self.register_buffer("device_marker", torch.empty(0), persistent=False)
        width, height = preprocessing.target_size(PROBE_SIZE[1], PROBE_SIZE[0])  # a fixed size, multiples of a patch
        was_training = self.module.training
        with torch.no_grad():
            self.module.eval()
            self.output_dim = int(self(torch.zeros(1, 3, height, width)).shape[1])
        self.module.train(was_training)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        output = self.module(images)
        if isinstance(output, (tuple, list)):
            output = output[0]
        if not isinstance(output, torch.Tensor):
            raise TypeError(
                f"the network returned {type(output).__name__}, "
                f"not a tensor of descriptors (or a tuple starting with one)"
            )
        return l2_normalize(output.flatten(1).float())

    def finalize(self, descriptors: torch.Tensor) -> torch.Tensor:
        return descriptors


class _Function(nn.Module):
    """A plain function as a module without parameters."""

    def __init__(self, function: Callable[[torch.Tensor], Any]) -> None:
        super().__init__()
        self.function = function

    def forward(self, images: torch.Tensor) -> Any:
        return self.function(images)


class ExternalDescriptor(TorchGlobalDescriptor):
    """A `ModuleNet` of ``module`` with ``preprocessing`` (the keys of `Preprocessing`), keyed by
    ``source`` (where the module came from); ``weights``: an optional local state dict (or
    locretrieval checkpoint) loaded into the module, every key used and none missing."""

    model = "external"

    def __init__(
        self,
        name: str,
        module: nn.Module | Callable,
        source: Mapping[str, Any],
        weights: str | os.PathLike | None,
        preprocessing: Mapping[str, Any],
        extraction: ExtractionSettings | Mapping[str, Any],
    ) -> None:
        preprocessing = Preprocessing(
            **{
                key: tuple(value) if isinstance(value, list) else value
                for key, value in plain(dict(preprocessing)).items()
            }
        )
        info = WeightsInfo(sha256=None)
        if weights is not None:
            if not isinstance(module, nn.Module):
                raise ValueError(f"model {name!r}: model.weights needs a module with parameters, not a function")
            info = load_state(module, Path(weights), name)
        super().__init__(name, ModuleNet(module, preprocessing), preprocessing, source, info, extraction)


def load_state(module: nn.Module, path: Path, name: str) -> WeightsInfo:
    """Load a state dict file into ``module`` strictly (restricted unpickler); its hash."""
    if not path.is_file():
        raise FileNotFoundError(f"model {name!r}: model.weights file {path} not found")
    state = embedded_checkpoint(load_torch_file(path))
    state = state.get("state_dict", state) if isinstance(state, Mapping) else state
    missing, unexpected = module.load_state_dict({k.removeprefix("module."): v for k, v in state.items()}, strict=False)
    if missing or unexpected:
        raise ValueError(
            f"model {name!r}: {path} does not fit the network: {len(missing)} keys missing (e.g. "
            f"{list(missing)[:3]}), {len(unexpected)} unexpected (e.g. {list(unexpected)[:3]})"
        )
    return WeightsInfo(sha256=content_sha256(path))


def hub_module(repo: str, entry: str, source: str, kwargs: Mapping[str, Any]) -> nn.Module:
    """``torch.hub.load(repo, entry, **kwargs)`` from a local folder or torch.hub's cache of a
    GitHub repo (never downloaded here: the error says where to get it)."""
    if source not in HUB_SOURCES:
        raise ValueError(f"model.source must be one of {list(HUB_SOURCES)}, got {source!r}")
    if source == "local" and not (Path(repo) / "hubconf.py").is_file():
        raise FileNotFoundError(
            f"model.repo: {Path(repo) / 'hubconf.py'} not found (model.source=local needs a folder with a hubconf.py)"
        )
    owner_name = repo.partition(":")[0].replace("/", "_")
    cached = sorted(Path(torch.hub.get_dir()).glob(f"{owner_name}_*"))
    if source == "github" and not cached:
        raise FileNotFoundError(
            f"torch.hub repo {repo!r} is not in torch.hub's cache "
            f"({torch.hub.get_dir()}) and nothing is downloaded here: run "
            f"torch.hub.load({repo!r}, {entry!r}) once where there is "
            f"internet (it fills that cache), or clone the repository "
            f"and use model.source=local model.repo=<folder>"
        )
    if source == "github" and ":" not in repo:  # the cached branch: torch.hub would ask GitHub which is the default
        branches = [folder.name.removeprefix(f"{owner_name}_") for folder in cached]
        repo = f"{repo}:{next((b for b in ('main', 'master') if b in branches), branches[0])}"
    try:
        return torch.hub.load(
            repo, entry, source=source, trust_repo=True, skip_validation=True, verbose=False, **dict(kwargs)
        )
    except (OSError, RuntimeError) as error:  # a weight download the entry point tried (no internet here)
        raise RuntimeError(
            f"torch.hub entry {entry!r} of {repo!r} failed: {error}. Its weights are fetched by the entry point "
            f"into {torch.hub.get_dir()}/checkpoints on a machine with internet; or pass model.weights=<local file>"
        ) from error


def callable_module(target: str, kwargs: Mapping[str, Any]) -> nn.Module | Callable:
    """The result of ``package.module:function(**kwargs)``: a module, or a function of images (a config
    the user runs names it: code, as the rest of their config)."""
    module_name, _, attribute = target.partition(":")
    if not module_name or not attribute:
        raise ValueError(f"model.target must be 'package.module:function', got {target!r}")
    try:
        builder = getattr(importlib.import_module(module_name), attribute)
    except (ImportError, AttributeError) as error:
        raise ImportError(f"model.target {target!r}: {error} (is its package on PYTHONPATH?)") from error
    return builder(**dict(kwargs))


class HubDescriptor(ExternalDescriptor):
    """``model=hub``: a torch.hub entry point (``repo``, ``entry``, ``source``, ``kwargs``)."""

    model = "hub"

    def __init__(
        self, name: str, repo: str, entry: str, source: str, kwargs: Mapping[str, Any], **settings: Any
    ) -> None:
        module = hub_module(str(repo), str(entry), str(source), plain(dict(kwargs)))
        identity = {"repo": str(repo), "entry": str(entry), "source": str(source), "kwargs": plain(dict(kwargs))}
        super().__init__(name, module, identity, **settings)


class CallableDescriptor(ExternalDescriptor):
    """``model=callable``: ``target`` (``package.module:function``) called with ``kwargs``."""

    model = "callable"

    def __init__(self, name: str, target: str, kwargs: Mapping[str, Any], **settings: Any) -> None:
        module = callable_module(str(target), plain(dict(kwargs)))
        # the code's content: a function has no state dict to hash, so an edit must change the key
        # (a copy, a fresh clone must not)
        code = content_sha256(inspect.getsourcefile(importlib.import_module(str(target).partition(":")[0])))[:16]
        super().__init__(name, module, {"target": str(target), "kwargs": plain(dict(kwargs)), "code": code}, **settings)
