"""AP-GeM (Revaud et al., ICCV 2019; paper Sec. 3.8.2) with NAVER's deep-image-retrieval weights.

ResNet -> GeM (learned power ``p``) -> FC (2048) -> L2 -> optional PCA whitening -> L2.
Input: ``(rgb / 255 - mean) / std`` with the checkpoint's ``preprocess`` statistics.

A dirtorch checkpoint (e.g. ``Resnet101-AP-GeM-LM18.pt``) is a ``torch.save``d dict:
``state_dict`` (dirtorch's ``ResNet_RMAC`` names, i.e. torchvision's ResNet names plus
``adpool.p`` and ``fc``; ``module.``-prefixed when saved from ``DataParallel``),
``model_options`` (``arch`` such as ``resnet101_rmac``, ``pooling``, ...), ``preprocess``
(``mean``, ``std``) and optionally ``pca``: scikit-learn ``PCA`` objects pickled under the
module path ``sklearn.decomposition.pca``, which current scikit-learn no longer has. The
file is read with torch's restricted unpickler, the PCA objects rebuilt as plain
attribute holders (`PicklePCA`) and turned into arrays; `convert_apgem` writes a checkpoint
that needs neither scikit-learn nor the pickled classes.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from locretrieval.models.extraction import IMAGENET_MEAN, IMAGENET_STD, ExtractionSettings, Preprocessing
from locretrieval.models.files.weights import (
    WEIGHT_SOURCES,
    Weights,
    content_sha256,
    read_weights,
    require_weights,
    save_checkpoint,
)
from locretrieval.models.networks import GeMPooling, RetrievalNet, build_retrieval_net, load_weights, pooling_settings
from locretrieval.models.torch_descriptor import TorchGlobalDescriptor
from locretrieval.models.trainable.backbones import TorchvisionBackbone

#: dirtorch architectures (``model_options['arch']``) and their torchvision backbones.
DIRTORCH_BACKBONES = {
    "resnet18_rmac": "resnet18",
    "resnet50_rmac": "resnet50",
    "resnet101_rmac": "resnet101",
    "resnet152_rmac": "resnet152",
}


class PicklePCA:
    """Stand-in for the scikit-learn ``PCA`` objects pickled in dirtorch checkpoints.

    The restricted unpickler rebuilds them as this class, which only holds the pickled
    attributes (``mean_``, ``components_``, ``explained_variance_``, ``whiten``, ...).
    """


#: Module paths under which scikit-learn's ``PCA`` appears in pickles (old and current).
_PCA_GLOBALS = [(PicklePCA, "sklearn.decomposition.pca.PCA"), (PicklePCA, "sklearn.decomposition._pca.PCA")]


@dataclass(frozen=True)
class PCAWhitening:
    """A PCA learned by dirtorch, as arrays: ``mean [D]``, ``components [C, D]``,
    ``explained_variance [C]``, and whether it whitens."""

    mean: np.ndarray
    components: np.ndarray
    explained_variance: np.ndarray
    whiten: bool

    @classmethod
    def from_attributes(cls, attributes: Mapping[str, Any], label: str) -> "PCAWhitening":
        missing = [key for key in ("mean_", "components_", "explained_variance_") if attributes.get(key) is None]
        if missing:
            raise ValueError(f"{label}: pickled PCA lacks {missing}")
        pca = cls(
            np.asarray(attributes["mean_"], dtype=np.float64),
            np.asarray(attributes["components_"], dtype=np.float64),
            np.asarray(attributes["explained_variance_"], dtype=np.float64),
            bool(attributes.get("whiten", False)),
        )
        if pca.components.shape[1:] != pca.mean.shape or pca.explained_variance.shape != pca.components.shape[:1]:
            raise ValueError(
                f"{label}: inconsistent PCA shapes mean {pca.mean.shape}, components {pca.components.shape}, "
                f"explained_variance {pca.explained_variance.shape}"
            )
        return pca

    def to_tensors(self) -> dict[str, torch.Tensor]:
        return {
            "mean": torch.from_numpy(self.mean),
            "components": torch.from_numpy(self.components),
            "explained_variance": torch.from_numpy(self.explained_variance),
            "whiten": torch.tensor(self.whiten),
        }

    @classmethod
    def from_tensors(cls, tensors: Mapping[str, torch.Tensor]) -> "PCAWhitening":
        return cls(
            *(tensors[key].numpy() for key in ("mean", "components", "explained_variance")), bool(tensors["whiten"])
        )

    def affine(
        self, power: float = 0.5, dims: int | None = None, multiplier: float = 1.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(W [dims, D], b [dims])`` with ``W x + b`` = dirtorch's ``whiten_features`` before its L2:
        ``(x - mean) @ components[:dims].T``, divided by ``multiplier * variance[:dims] ** power``
        when the PCA whitens."""
        weight = self.components[:dims]
        if self.whiten:
            weight = weight / (multiplier * self.explained_variance[:dims, None] ** power)
        return weight, -weight @ self.mean


@dataclass
class APGeMWeights:
    """An AP-GeM network's state dict (`build_apgem_network` names) and what comes with it."""

    state_dict: dict[str, torch.Tensor]
    backbone: str
    out_dim: int
    mean: tuple[float, ...]
    std: tuple[float, ...]
    pcas: dict[str, PCAWhitening]


def _network_name(key: str) -> str:
    if key == "adpool.p":
        return "pooling.p"
    if key.startswith("fc."):
        return "whitening." + key[3:]
    return "backbone." + key


def read_apgem_weights(path: str | os.PathLike, architecture: Mapping[str, Any] | None = None) -> APGeMWeights:
    """Read a dirtorch checkpoint (restricted unpickling; PCA objects become arrays) or a
    checkpoint `convert_apgem` wrote (`read_weights`); raise unless it holds ``architecture``
    (``backbone``, ``out_dim``; ``None`` accepts any)."""
    weights = read_weights(path, "apgem", architecture or {}, _read_dirtorch, allowed=_PCA_GLOBALS)
    if weights.checkpoint:
        pcas = {name: PCAWhitening.from_tensors(tensors) for name, tensors in weights.extra.get("pca", {}).items()}
    else:
        pcas = dict(weights.extra["pca"])
    return APGeMWeights(
        dict(weights.state_dict),
        weights.architecture["backbone"],
        int(weights.architecture["out_dim"]),
        tuple(float(v) for v in weights.preprocessing["mean"]),
        tuple(float(v) for v in weights.preprocessing["std"]),
        pcas,
    )


def _read_dirtorch(path: Path, content: Any) -> Weights:
    """The weights of a dirtorch checkpoint's content (`AuthorsReader`); PCAs as `PCAWhitening` in ``extra``."""
    if not isinstance(content, dict) or "state_dict" not in content:
        raise ValueError(f"{path}: not a dirtorch checkpoint (a dict with 'state_dict', 'model_options')")
    options = dict(content.get("model_options") or {})
    arch = options.get("arch")
    if arch not in DIRTORCH_BACKBONES:
        raise ValueError(f"{path}: model_options arch {arch!r} is not one of {sorted(DIRTORCH_BACKBONES)}")
    if (
        not str(options.get("pooling", "gem")).startswith("gem")
        or options.get("without_fc")
        or options.get("norm_features")
    ):
        raise ValueError(f"{path}: only GeM pooling followed by the FC layer is supported; model_options {options}")
    state = {_network_name(key.removeprefix("module.")): value for key, value in content["state_dict"].items()}
    if "whitening.weight" not in state:
        raise ValueError(f"{path}: state_dict has no 'fc.weight' (the 2048-D FC layer)")
    preprocess = content.get("preprocess") or {}
    pcas = {
        str(name): PCAWhitening.from_attributes(
            vars(pca) if isinstance(pca, PicklePCA) else pca, f"{path} pca[{name!r}]"
        )
        for name, pca in (content.get("pca") or {}).items()
    }
    architecture = {"backbone": DIRTORCH_BACKBONES[arch], "out_dim": int(state["whitening.weight"].shape[0])}
    preprocessing = {"mean": preprocess.get("mean", IMAGENET_MEAN), "std": preprocess.get("std", IMAGENET_STD)}
    return Weights(state, architecture, preprocessing, {"pca": pcas})


def convert_apgem(source: str | os.PathLike, destination: str | os.PathLike) -> None:
    """Write a dirtorch checkpoint as a plain locretrieval checkpoint (PCA as tensors)."""
    weights = read_apgem_weights(source)
    save_checkpoint(
        destination,
        "apgem",
        {"backbone": weights.backbone, "out_dim": weights.out_dim},
        {"mean": weights.mean, "std": weights.std},
        weights.state_dict,
        {
            "pca": {name: pca.to_tensors() for name, pca in weights.pcas.items()},
            "source_sha256": content_sha256(source),
        },
    )


def build_apgem_network(
    backbone: str = "resnet101", out_dim: int = 2048, projection_dim: int | None = None
) -> RetrievalNet:
    """GeM (learned ``p``) -> FC ``out_dim`` as the whitening -> optional PCA as the projection, on
    torchvision's ``backbone``."""
    return build_retrieval_net(
        TorchvisionBackbone(backbone),
        pooling_settings(partial(GeMPooling, p=3.0, trainable=True)),
        out_dim,
        projection_dim,
    )


class APGeMDescriptor(TorchGlobalDescriptor):
    """AP-GeM from a dirtorch checkpoint or a checkpoint `convert_apgem` wrote.

    ``pca``: name of a PCA stored in the checkpoint (e.g. ``Landmarks_clean``) to whiten
    with, or ``None`` (the benchmark's setting); ``pca_power``, ``pca_dims``,
    ``pca_multiplier``: dirtorch's ``whitenp``, ``whitenv``, ``whitenm``.
    """

    model = "apgem"

    def __init__(
        self,
        name: str,
        weights: str | os.PathLike | None,
        backbone: str,
        out_dim: int,
        pca: str | None,
        pca_power: float,
        pca_dims: int | None,
        pca_multiplier: float,
        max_side: int | None,
        scales: Sequence[float],
        extraction: ExtractionSettings | Mapping[str, Any],
    ) -> None:
        path = require_weights(weights, WEIGHT_SOURCES["apgem"], name)
        declared = {"backbone": str(backbone), "out_dim": int(out_dim)}
        loaded = read_apgem_weights(path, declared)
        state = dict(loaded.state_dict)
        projection_dim = None
        if pca is not None:
            if pca not in loaded.pcas:
                raise ValueError(f"{path}: no PCA named {pca!r}; the checkpoint holds {sorted(loaded.pcas)}")
            weight, bias = loaded.pcas[pca].affine(float(pca_power), pca_dims, float(pca_multiplier))
            state["projection.weight"] = torch.from_numpy(weight.astype(np.float32))
            state["projection.bias"] = torch.from_numpy(bias.astype(np.float32))
            projection_dim = weight.shape[0]
        network, info = load_weights(
            lambda: build_apgem_network(loaded.backbone, loaded.out_dim, projection_dim), state, path
        )
        architecture = {
            **declared,
            "pca": pca,
            "pca_power": float(pca_power) if pca else None,
            "pca_dims": pca_dims if pca else None,
            "pca_multiplier": float(pca_multiplier) if pca else None,
        }
        preprocessing = Preprocessing(max_side=max_side, scales=tuple(scales), mean=loaded.mean, std=loaded.std)
        super().__init__(name, network, preprocessing, architecture, info, extraction)
