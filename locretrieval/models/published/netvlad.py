"""NetVLAD (Arandjelovic et al., CVPR 2016; paper Sec. 3.8.2) with the authors' MATLAB weights.

VGG16 up to conv5_3 (no final ReLU) -> per-location L2 -> NetVLAD (64 clusters of 512-D,
soft assignment without bias) -> intra-normalisation -> L2 -> whitening (PCA, 32768 -> 4096,
with bias) -> L2. Input: RGB in [0, 255] minus the training set's average colour.

The authors' MatConvNet model ``vd16_pitts30k_conv5_3_vlad_preL2_intra_white.mat`` stores
objects scipy cannot read; its struct form (``net_class2struct.m``, e.g. hloc's
``Pitts30K_struct.mat``) holds ``net.layers`` (a cell of structs with ``name``, ``type``,
``weights``) and ``net.meta.normalization.averageImage``. In it:

- conv filters are ``S x S x IN x OUT`` (height, width, input, output), biases ``OUT``;
- the first 29 layers are VGG16's conv1_1 ... conv5_3 with ReLUs and 4 max-pools, in
  torchvision's ``features`` order;
- the first weighted layer after them is the VLAD core: ``{assignment filters D x K,
  centres D x K}``, the centres stored negated (MATLAB adds them to the features);
- the next weighted layer, if any, is the whitening as a 1x1 convolution,
  ``1 x 1 x (D*K) x OUT`` plus an ``OUT`` bias, whose input index is MATLAB's column-major
  flattening of the ``K x D`` VLAD matrix: cluster fastest (see `NetVLADPooling`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io
import torch
from torch import nn

from locretrieval.bounded_files import check_mat
from locretrieval.models.extraction import ExtractionSettings, Preprocessing
from locretrieval.models.files.weights import (
    WEIGHT_SOURCES,
    Weights,
    content_sha256,
    read_weights,
    require_weights,
    save_checkpoint,
)
from locretrieval.models.networks import (
    NetVLADPooling,
    RetrievalNet,
    build_retrieval_net,
    load_weights,
    pooling_settings,
    torchvision_trunk,
)
from locretrieval.models.torch_descriptor import TorchGlobalDescriptor
from locretrieval.models.trainable.backbones import TorchvisionBackbone

#: MatConvNet layers of VGG16 up to conv5_3 (13 convolutions, 12 ReLUs, 4 max-pools).
VGG16_TRUNK_LAYERS = 29


def build_netvlad_network(clusters: int = 64, whiten_dim: int | None = 4096) -> RetrievalNet:
    """The authors' architecture: NetVLAD (``clusters`` centres) on VGG16, optional whitening."""
    return build_retrieval_net(
        TorchvisionBackbone("vgg16"), pooling_settings(partial(NetVLADPooling, clusters=clusters)), whiten_dim
    )


def _layer_weights(layer: Any) -> list[np.ndarray]:
    """A struct layer's ``weights`` cell as a list (scipy squeezes a 1-element cell to its element)."""
    weights = getattr(layer, "weights", None)
    if weights is None:
        return []
    if isinstance(weights, np.ndarray) and weights.dtype == object:
        return [np.asarray(w, dtype=np.float32) for w in weights.ravel()]
    weights = np.asarray(weights)
    return [weights.astype(np.float32)] if weights.size else []


def _layer_label(layers: Sequence[Any], index: int) -> str:
    return f"layer {index + 1} ({getattr(layers[index], 'name', '?')!s})"


def read_netvlad_struct(path: str | os.PathLike) -> tuple[dict[str, torch.Tensor], np.ndarray]:
    """State dict of `build_netvlad_network` and the average RGB colour (0-255) from a struct ``.mat``."""
    path = Path(path)
    check_mat(path)  # compressed elements and cell or struct sizes within limits.compression_ratio
    try:
        mat = scipy.io.loadmat(path, struct_as_record=False, squeeze_me=True)
    except NotImplementedError as error:  # MATLAB v7.3 (HDF5) files
        raise ValueError(f"{path}: a MATLAB v7.3 file; re-save it with save(..., '-v7'): {error}") from error
    except (ValueError, TypeError, IndexError, OSError) as error:  # not a MATLAB file at all
        raise ValueError(
            f"{path}: not a MATLAB .mat file holding NetVLAD's struct 'net' ({type(error).__name__}: {error})"
        ) from None
    net = mat.get("net")
    if net is None or not hasattr(net, "layers"):
        raise ValueError(
            f"{path}: no struct variable 'net' with 'layers' (found "
            f"{sorted(k for k in mat if not k.startswith('__'))}); "
            "a MatConvNet object file must first be converted with net_class2struct.m"
        )
    layers = list(np.atleast_1d(net.layers))
    with torch.device("meta"):  # shapes only
        trunk, _ = torchvision_trunk("vgg16")
    state: dict[str, torch.Tensor] = {}
    for index, module in enumerate(trunk.features):
        if not isinstance(module, nn.Conv2d):
            continue
        weights = _layer_weights(layers[index]) if index < len(layers) else []
        expected = (module.kernel_size[0], module.kernel_size[1], module.in_channels, module.out_channels)
        if len(weights) != 2 or weights[0].shape != expected or weights[1].size != module.out_channels:
            found = [w.shape for w in weights]
            raise ValueError(
                f"{path}: {_layer_label(layers, index)} should be VGG16's conv with filters {expected} and "
                f"{module.out_channels} biases; found weights {found}"
            )
        state[f"backbone.features.{index}.weight"] = torch.from_numpy(weights[0]).permute(3, 2, 0, 1).contiguous()
        state[f"backbone.features.{index}.bias"] = torch.from_numpy(weights[1].reshape(-1))
    weighted = [i for i in range(VGG16_TRUNK_LAYERS, len(layers)) if _layer_weights(layers[i])]
    if not weighted:
        raise ValueError(f"{path}: no NetVLAD layer after VGG16's conv5_3 (layer {VGG16_TRUNK_LAYERS})")
    vlad = _layer_weights(layers[weighted[0]])
    if len(vlad) != 2 or vlad[0].ndim != 2 or vlad[0].shape != vlad[1].shape:
        raise ValueError(
            f"{path}: {_layer_label(layers, weighted[0])} should hold the VLAD assignment filters and centres "
            f"(both D x K); found {[w.shape for w in vlad]}"
        )
    dim, clusters = vlad[0].shape
    state["pooling.assignment.weight"] = torch.from_numpy(vlad[0].T.copy()).reshape(clusters, dim, 1, 1)
    state["pooling.centers"] = torch.from_numpy(-vlad[1].T.copy())
    if len(weighted) > 1:
        whitening = _layer_weights(layers[weighted[1]])
        matrix = (
            whitening[0].reshape(dim * clusters, -1)
            if whitening and whitening[0].size % (dim * clusters) == 0
            else None
        )
        if len(whitening) != 2 or matrix is None or whitening[1].size != matrix.shape[1]:
            raise ValueError(
                f"{path}: {_layer_label(layers, weighted[1])} should be the whitening, 1 x 1 x {dim * clusters} x OUT "
                f"filters and OUT biases; found {[w.shape for w in whitening]}"
            )
        state["whitening.weight"] = torch.from_numpy(matrix.T.copy())
        state["whitening.bias"] = torch.from_numpy(whitening[1].reshape(-1))
    average = np.asarray(net.meta.normalization.averageImage, dtype=np.float64).reshape(-1, 3).mean(axis=0)
    return state, average


def architecture_of(state_dict: dict[str, torch.Tensor]) -> dict[str, Any]:
    whitening = state_dict.get("whitening.weight")
    return {
        "clusters": int(state_dict["pooling.centers"].shape[0]),
        "whiten_dim": None if whitening is None else int(whitening.shape[0]),
    }


def _read_struct(path: Path, content: Any) -> Weights:
    """The weights of the authors' struct ``.mat`` (`AuthorsReader`): inputs ``rgb - average`` in 0-255."""
    if content is not None:
        raise ValueError(f"{path}: neither a struct .mat nor a locretrieval NetVLAD checkpoint")
    state, average = read_netvlad_struct(path)
    return Weights(state, architecture_of(state), {"mean": list(average / 255.0), "std": [1 / 255.0] * 3})


def convert_netvlad(source: str | os.PathLike, destination: str | os.PathLike) -> None:
    """Write the struct ``.mat`` as a plain locretrieval checkpoint (no scipy/MATLAB layout needed)."""
    state, average = read_netvlad_struct(source)
    preprocessing = {"mean": (average / 255.0).tolist(), "std": [1 / 255.0] * 3}
    save_checkpoint(
        destination, "netvlad", architecture_of(state), preprocessing, state, {"source_sha256": content_sha256(source)}
    )


class NetVLADDescriptor(TorchGlobalDescriptor):
    """NetVLAD from the authors' struct ``.mat`` or a checkpoint `convert_netvlad` wrote.

    ``clusters``/``whiten_dim`` declare the architecture the file must hold (64 / 4096 for
    Pitts30k; ``whiten_dim: null`` for a model without whitening).
    """

    model = "netvlad"

    def __init__(
        self,
        name: str,
        weights: str | os.PathLike | None,
        clusters: int,
        whiten_dim: int | None,
        max_side: int | None,
        scales: Sequence[float],
        extraction: ExtractionSettings | Mapping[str, Any],
    ) -> None:
        path = require_weights(weights, WEIGHT_SOURCES["netvlad"], name)
        architecture = {"clusters": int(clusters), "whiten_dim": None if whiten_dim is None else int(whiten_dim)}
        weights = read_weights(
            path, self.model, architecture, _read_struct, authors_file=lambda file: file.suffix.lower() == ".mat"
        )
        network, info = load_weights(lambda: build_netvlad_network(**architecture), weights.state_dict, path)
        mean, std = weights.preprocessing["mean"], weights.preprocessing["std"]
        preprocessing = Preprocessing(max_side=max_side, scales=tuple(scales), mean=tuple(mean), std=tuple(std))
        super().__init__(name, network, preprocessing, architecture, info, extraction)
