"""The trainable models: GeM or NetVLAD pooling on any torchvision backbone, optional whitening.

Weights come from a local file: a torchvision ImageNet checkpoint (the backbone; the head
then needs ``random_init``) or a locretrieval checkpoint (`TorchGlobalDescriptor.save_checkpoint`,
everything). Randomly initialised parameters are only allowed with ``random_init: true``;
the model's name then carries ``_random-init`` and its identity lists them.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from locretrieval.models.extraction import IMAGENET_MEAN, IMAGENET_STD, ExtractionSettings, Preprocessing
from locretrieval.models.heads import GeMPooling, NetVLADPooling, RetrievalNet, torchvision_trunk
from locretrieval.models.torch_descriptor import TorchGlobalDescriptor, WeightsInfo, build_network
from locretrieval.models.weights import (
    MissingWeightsError,
    check_checkpoint,
    content_sha256,
    is_checkpoint,
    load_torch_file,
    require_weights,
    torchvision_source,
)

#: torchvision classifier parameters that a backbone checkpoint holds and the trunk drops.
_CLASSIFIER_PREFIXES = ("fc.", "classifier.")


def build_gem_network(
    backbone: str,
    p: float = 3.0,
    trainable_p: bool = True,
    whiten_dim: int | None = None,
    projection_dim: int | None = None,
) -> RetrievalNet:
    """GeM on a torchvision trunk, optional whitening (``whiten_dim``) and final projection
    (``projection_dim``, applied after multi-scale aggregation)."""
    trunk, channels = torchvision_trunk(backbone)
    whitening = nn.Linear(channels, whiten_dim) if whiten_dim else None
    projection = nn.Linear(whiten_dim or channels, projection_dim) if projection_dim else None
    return RetrievalNet(trunk, GeMPooling(p, trainable=trainable_p), channels, whitening, projection)


def build_netvlad_head_network(backbone: str, clusters: int = 64, whiten_dim: int | None = None) -> RetrievalNet:
    trunk, channels = torchvision_trunk(backbone)
    pooling = NetVLADPooling(channels, clusters)
    whitening = nn.Linear(pooling.output_dim, whiten_dim) if whiten_dim else None
    return RetrievalNet(trunk, pooling, pooling.output_dim, whitening)


def read_trainable_weights(path: Path, model: str, architecture: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """State dict from our checkpoint of ``model``, or a torchvision backbone state dict (prefixed)."""
    content = load_torch_file(path)
    if is_checkpoint(content):
        check_checkpoint(content, path, model, architecture)
        return content["state_dict"]
    if isinstance(content, Mapping) and content and all(isinstance(v, torch.Tensor) for v in content.values()):
        return {f"backbone.{key}": value for key, value in content.items() if not key.startswith(_CLASSIFIER_PREFIXES)}
    raise ValueError(f"{path}: neither a torchvision state dict nor a locretrieval checkpoint of model {model!r}")


class _TrainableDescriptor(TorchGlobalDescriptor):
    def __init__(
        self,
        name: str,
        factory: Callable[[], RetrievalNet],
        architecture: Mapping[str, Any],
        weights: str | os.PathLike | None,
        random_init: bool,
        seed: int,
        preprocessing: Preprocessing,
        settings: ExtractionSettings,
        memmap_dir: str | os.PathLike | None,
        configured: Mapping[str, torch.Tensor] | None = None,
    ) -> None:
        """``configured``: initial values set by the configuration (GeM's ``p``), used where the
        weight file has none (a torchvision checkpoint)."""
        source = torchvision_source(architecture["backbone"])
        if weights is None and not random_init:
            raise MissingWeightsError(
                f"model {name!r}: no model.weights path is set. Give a torchvision checkpoint ({source.expected}; "
                f"{source.publisher}) or a locretrieval checkpoint, or set model.random_init=true for random weights"
            )
        state, sha256 = dict(configured or {}), None
        if weights is not None:
            path = require_weights(weights, source, name)
            state.update(read_trainable_weights(path, self.model, architecture))
            sha256 = content_sha256(path)
        network, random_parameters = build_network(factory, state or None, str(weights), bool(random_init), int(seed))
        super().__init__(
            name, network, preprocessing, architecture, WeightsInfo(sha256, random_parameters, int(seed)), settings, memmap_dir
        )


class GeMHeadDescriptor(_TrainableDescriptor):
    """GeM pooling (power ``p``, learned when ``trainable_p``) on a torchvision ``backbone``."""

    model = "gem"

    def __init__(
        self,
        name: str = "gem",
        backbone: str = "resnet50",
        weights: str | os.PathLike | None = None,
        random_init: bool = False,
        seed: int = 0,
        p: float = 3.0,
        trainable_p: bool = True,
        whiten_dim: int | None = None,
        max_side: int | None = 1024,
        scales: Sequence[float] = (1.0,),
        memmap_dir: str | os.PathLike | None = None,
        **extraction: Any,
    ) -> None:
        architecture = {"backbone": str(backbone), "p": float(p), "trainable_p": bool(trainable_p), "whiten_dim": whiten_dim}
        super().__init__(
            name,
            lambda: build_gem_network(str(backbone), float(p), bool(trainable_p), whiten_dim),
            architecture,
            weights,
            random_init,
            seed,
            Preprocessing(max_side=max_side, scales=tuple(scales), mean=IMAGENET_MEAN, std=IMAGENET_STD),
            ExtractionSettings.from_options(name, extraction),
            memmap_dir,
            {"pooling.p": torch.tensor([float(p)])},
        )


class NetVLADHeadDescriptor(_TrainableDescriptor):
    """NetVLAD pooling (``clusters`` centres) on a torchvision ``backbone``."""

    model = "netvlad_head"

    def __init__(
        self,
        name: str = "netvlad_head",
        backbone: str = "vgg16",
        weights: str | os.PathLike | None = None,
        random_init: bool = False,
        seed: int = 0,
        clusters: int = 64,
        whiten_dim: int | None = None,
        max_side: int | None = 1024,
        scales: Sequence[float] = (1.0,),
        memmap_dir: str | os.PathLike | None = None,
        **extraction: Any,
    ) -> None:
        architecture = {"backbone": str(backbone), "clusters": int(clusters), "whiten_dim": whiten_dim}
        super().__init__(
            name,
            lambda: build_netvlad_head_network(str(backbone), int(clusters), whiten_dim),
            architecture,
            weights,
            random_init,
            seed,
            Preprocessing(max_side=max_side, scales=tuple(scales), mean=IMAGENET_MEAN, std=IMAGENET_STD),
            ExtractionSettings.from_options(name, extraction),
            memmap_dir,
        )
