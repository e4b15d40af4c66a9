"""DELG's global branch (Cao et al., ECCV 2020; paper Sec. 3.8.2), model ``r101delg_gldv2clean``.

TF-Slim ResNet-v1-101 -> GeM (p = 3, fixed) -> FC whitening (2048, with bias) -> L2 at each
scale in {0.7071, 1, 1.4142} of the image shrunk to at most 1024 px; the per-scale
descriptors are summed and L2-normalised (DELF's ``extractor.py``: ``use_pca: false``,
``image_scales_ind: 3, 4, 5``, ``max_image_size: 1024``). Input: ``(rgb - 128) / 128``.

The authors ship only a TensorFlow-1 SavedModel. Its variables are read (behind the
optional ``tensorflow`` dependency, `read_tf_variables`) and renamed by
`delg_state_dict_from_tf`, a pure function of ``{name: array}``.

What this assumes and could not be checked here (no TensorFlow, no internet): that the
backbone is ``tf_slim.nets.resnet_v1`` (variables ``resnet_v1_101/conv1/weights``,
``resnet_v1_101/blockB/unit_U/bottleneck_v1/{conv1,conv2,conv3,shortcut}/{weights,
BatchNorm/...}``; the DELF TF2 code says its ``block3_strides`` exists "to make it
compatible with tf.slim ResNet implementation"), slim's batch-norm epsilon 1e-5, that
the whitening is the only kernel outside the backbone with 2048 inputs (or is named with
``whitening_scope``), and that the exported graph resizes as ``tf.image.resize`` (half-pixel
centres). Parity of the converted model with the TensorFlow model has NOT been shown; the
published DELG features, read with the ``precomputed`` model, remain the supported path.
"""

from __future__ import annotations

import functools
import os
import re
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torchvision.models.resnet import Bottleneck

from locretrieval.cache import load_arrays
from locretrieval.errors import FIX_DATA_FILE
from locretrieval.models.extraction import ExtractionSettings, Preprocessing
from locretrieval.models.files.weights import (
    WEIGHT_SOURCES,
    Weights,
    content_sha256,
    read_weights,
    require_weights,
    save_checkpoint,
)
from locretrieval.models.networks import GeMPooling, RetrievalNet, load_weights
from locretrieval.models.torch_descriptor import TorchGlobalDescriptor

#: DELF config ``r101delg_gldv2clean_config.pbtxt``: scales 3, 4, 5 of its pyramid.
DELG_SCALES = (0.70710677, 1.0, 1.4142135)
DELG_MAX_SIDE = 1024
#: ``(x - 128) / 128`` as ``(x / 255 - mean) / std``.
DELG_MEAN = DELG_STD = (128.0 / 255.0,) * 3
#: Units per block of ResNet-v1-101 and the base depths / strides of slim's blocks.
RESNET_V1_101_UNITS = (3, 4, 23, 3)
_BASE_DEPTHS = (64, 128, 256, 512)
_BLOCK_STRIDES = (2, 2, 2, 1)


class SamePaddingMaxPool2d(nn.Module):
    """TensorFlow's ``SAME`` max-pooling: pads ``(total // 2, total - total // 2)`` with -inf."""

    def __init__(self, kernel_size: int, stride: int) -> None:
        super().__init__()
        self.kernel_size, self.stride = kernel_size, stride

    def _padding(self, size: int) -> tuple[int, int]:
        total = max((-(-size // self.stride) - 1) * self.stride + self.kernel_size - size, 0)
        return total // 2, total - total // 2

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        padding = (*self._padding(x.shape[3]), *self._padding(x.shape[2]))
        return F.max_pool2d(F.pad(x, padding, value=float("-inf")), self.kernel_size, self.stride)


def slim_resnet_v1(units: Sequence[int] = RESNET_V1_101_UNITS, bn_eps: float = 1e-5) -> nn.Sequential:
    """TF-Slim's ``resnet_v1`` trunk (torchvision ``Bottleneck`` units, slim's layout).

    Differences from torchvision's ResNet: each block's stride sits on its *last* unit
    (3x3 conv), whose shortcut is then a 1x1 stride-2 subsampling rather than a
    convolution; the stem max-pool pads like TensorFlow's ``SAME``. Module names:
    ``conv1``, ``bn1``, ``block{1..4}.{unit-1}.{conv1,bn1,...,downsample}``.
    """
    norm = functools.partial(nn.BatchNorm2d, eps=bn_eps)
    modules: list[tuple[str, nn.Module]] = [
        ("conv1", nn.Conv2d(3, 64, kernel_size=7, stride=2, padding=3, bias=False)),
        ("bn1", norm(64)),
        ("relu", nn.ReLU(inplace=True)),
        ("pool1", SamePaddingMaxPool2d(3, 2)),
    ]
    channels = 64
    for block, (count, depth, stride) in enumerate(zip(units, _BASE_DEPTHS, _BLOCK_STRIDES), start=1):
        unit_modules = []
        for unit in range(count):
            unit_stride = stride if unit == count - 1 else 1
            if channels != depth * 4:
                shortcut = nn.Sequential(
                    nn.Conv2d(channels, depth * 4, 1, stride=unit_stride, bias=False), norm(depth * 4)
                )
            else:
                shortcut = nn.MaxPool2d(kernel_size=1, stride=unit_stride) if unit_stride != 1 else None
            unit_modules.append(Bottleneck(channels, depth, stride=unit_stride, downsample=shortcut, norm_layer=norm))
            channels = depth * 4
        modules.append((f"block{block}", nn.Sequential(*unit_modules)))
    return nn.Sequential(OrderedDict(modules))


def build_delg_network(
    units: Sequence[int] = RESNET_V1_101_UNITS, whiten_dim: int = 2048, gem_power: float = 3.0, bn_eps: float = 1e-5
) -> RetrievalNet:
    trunk = slim_resnet_v1(units, bn_eps)
    return RetrievalNet(trunk, GeMPooling(2048, gem_power, trainable=False), 2048, nn.Linear(2048, whiten_dim))


_BACKBONE_VARIABLE = re.compile(
    r"(?:^|/)resnet_v1_\d+/(?:(?P<stem>conv1)|block(?P<block>\d)/unit_(?P<unit>\d+)/bottleneck_v1/"
    r"(?P<layer>conv[123]|shortcut))/(?P<param>weights|BatchNorm/(?:gamma|beta|moving_mean|moving_variance))$"
)
_BN_NAMES = {"gamma": "weight", "beta": "bias", "moving_mean": "running_mean", "moving_variance": "running_var"}
_KERNEL_SUFFIXES = ("/weights", "/kernel")
_BIAS_SUFFIXES = ("/biases", "/bias")


def _backbone_name(match: re.Match) -> str:
    """Our parameter name for a slim ResNet variable."""
    if match["stem"]:
        conv, norm = "backbone.conv1", "backbone.bn1"
    else:
        unit = f"backbone.block{match['block']}.{int(match['unit']) - 1}"
        layer = match["layer"]
        if layer == "shortcut":
            conv, norm = f"{unit}.downsample.0", f"{unit}.downsample.1"
        else:
            conv, norm = f"{unit}.{layer}", f"{unit}.bn{layer[-1]}"
    param = match["param"]
    return f"{conv}.weight" if param == "weights" else f"{norm}.{_BN_NAMES[param.split('/')[1]]}"


def _whitening_variables(variables: Mapping[str, np.ndarray], scope: str | None) -> tuple[str, str]:
    """Names of the whitening kernel and bias: under ``scope``, or the only kernel with 2048 inputs."""
    kernels = [
        name
        for name, value in variables.items()
        if name.endswith(_KERNEL_SUFFIXES)
        and not _BACKBONE_VARIABLE.search(name)
        and (scope is None or name.rsplit("/", 1)[0].endswith(scope))
        and np.ndim(value) in (2, 4)
        and np.shape(value)[-2] == 2048
        and np.prod(np.shape(value)[:-2]) == 1
    ]
    if len(kernels) != 1:
        where = f"under scope {scope!r}" if scope else "outside the ResNet with 2048 inputs"
        raise ValueError(f"expected one whitening kernel {where}, found {kernels}; set whitening_scope")
    prefix = kernels[0].rsplit("/", 1)[0]
    biases = [prefix + suffix for suffix in _BIAS_SUFFIXES if prefix + suffix in variables]
    if not biases:
        raise ValueError(f"whitening kernel {kernels[0]} has no bias ({prefix}/biases or {prefix}/bias)")
    return kernels[0], biases[0]


def delg_state_dict_from_tf(
    variables: Mapping[str, np.ndarray], gem_power: float = 3.0, whitening_scope: str | None = None
) -> dict[str, torch.Tensor]:
    """Rename and transpose DELG's TensorFlow variables into `build_delg_network`'s state dict.

    Variable names may carry a ``:0`` suffix and any scope prefix before ``resnet_v1_N/``.
    Convolution kernels ``[H, W, IN, OUT]`` become ``[OUT, IN, H, W]``; the whitening kernel
    ``[IN, OUT]`` (dense) or ``[1, 1, IN, OUT]`` (1x1 conv) becomes ``[OUT, IN]``. Variables of
    DELG's local branch (attention, autoencoder) and training state are ignored.
    """
    variables = {name.removesuffix(":0"): value for name, value in variables.items()}
    state: dict[str, torch.Tensor] = {}
    for name, value in variables.items():
        match = _BACKBONE_VARIABLE.search(name)
        if match is None:
            continue
        array = np.asarray(value, dtype=np.float32)
        if match["param"] == "weights":
            array = array.transpose(3, 2, 0, 1)
        key = _backbone_name(match)
        if key in state:
            raise ValueError(f"two variables map to {key}, the second is {name}")
        state[key] = torch.from_numpy(np.ascontiguousarray(array))
    kernel, bias = _whitening_variables(variables, whitening_scope)
    matrix = np.asarray(variables[kernel], dtype=np.float32)
    state["whitening.weight"] = torch.from_numpy(np.ascontiguousarray(matrix.reshape(matrix.shape[-2:]).T))
    state["whitening.bias"] = torch.from_numpy(np.asarray(variables[bias], dtype=np.float32).reshape(-1))
    state["pooling.p"] = torch.tensor([float(gem_power)])
    return state


def units_of(state_dict: Mapping[str, torch.Tensor]) -> tuple[int, ...]:
    """Units per block found in a DELG state dict."""
    counts = [0, 0, 0, 0]
    for key in state_dict:
        match = re.match(r"backbone\.block(\d)\.(\d+)\.conv1\.weight$", key)
        if match:
            block = int(match[1]) - 1
            counts[block] = max(counts[block], int(match[2]) + 1)
    return tuple(counts)


def read_tf_variables(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every variable of a TensorFlow SavedModel folder or checkpoint prefix, or of an ``.npz``.

    SavedModels need the optional ``tensorflow`` dependency; an ``.npz`` of ``{name: array}``
    (e.g. dumped on a machine with TensorFlow) needs nothing.
    """
    path = Path(path)
    if path.suffix == ".npz":
        return load_arrays(path, FIX_DATA_FILE)
    try:
        import tensorflow as tf
    except ImportError as error:
        raise ImportError(
            f"reading the TensorFlow model {path} needs tensorflow: pip install 'locretrieval[tensorflow]', or dump "
            "its variables to an .npz elsewhere, then run scripts/convert_weights.py delg"
        ) from error
    prefix = path / "variables" / "variables" if path.is_dir() else path
    reader = tf.train.load_checkpoint(str(prefix))
    return {name: reader.get_tensor(name) for name in reader.get_variable_to_shape_map()}


def convert_delg(
    source: str | os.PathLike,
    destination: str | os.PathLike,
    gem_power: float = 3.0,
    whitening_scope: str | None = None,
) -> None:
    """Write DELG's TensorFlow weights (SavedModel or ``.npz``) as a locretrieval checkpoint."""
    state = delg_state_dict_from_tf(read_tf_variables(source), gem_power, whitening_scope)
    architecture = {
        "units": units_of(state),
        "whiten_dim": int(state["whitening.weight"].shape[0]),
        "gem_power": gem_power,
    }
    save_checkpoint(
        destination,
        "delg",
        architecture,
        {"mean": DELG_MEAN, "std": DELG_STD},
        state,
        {"source_sha256": content_sha256(source)},
    )


class DELGDescriptor(TorchGlobalDescriptor):
    """DELG global descriptor from a converted checkpoint (or the TF model with tensorflow).

    See the module docstring for what was and was not verified against TensorFlow.
    ``bn_eps``: batch-norm epsilon of the TF model (slim's default 1e-5).
    """

    model = "delg"

    def __init__(
        self,
        name: str,
        weights: str | os.PathLike | None,
        units: Sequence[int],
        whiten_dim: int,
        gem_power: float,
        bn_eps: float,
        whitening_scope: str | None,
        max_side: int | None,
        scales: Sequence[float],
        extraction: ExtractionSettings | Mapping[str, Any],
    ) -> None:
        path = require_weights(weights, WEIGHT_SOURCES["delg"], name)
        architecture = {
            "units": tuple(int(u) for u in units),
            "whiten_dim": int(whiten_dim),
            "gem_power": float(gem_power),
        }

        def read_tensorflow(file: Path, content: Any) -> Weights:
            """DELG's TensorFlow variables (a SavedModel folder or an ``.npz``), as `AuthorsReader`."""
            if content is not None:
                raise ValueError(f"{file}: neither a TensorFlow model nor a locretrieval DELG checkpoint")
            return Weights(delg_state_dict_from_tf(read_tf_variables(file), float(gem_power), whitening_scope))

        weights = read_weights(
            path,
            self.model,
            architecture,
            read_tensorflow,
            authors_file=lambda file: file.is_dir() or file.suffix == ".npz",
        )
        network, info = load_weights(
            lambda: build_delg_network(
                architecture["units"], architecture["whiten_dim"], architecture["gem_power"], float(bn_eps)
            ),
            weights.state_dict,
            path,
        )
        preprocessing = Preprocessing(max_side=max_side, scales=tuple(scales), mean=DELG_MEAN, std=DELG_STD)
        super().__init__(name, network, preprocessing, {**architecture, "bn_eps": float(bn_eps)}, info, extraction)
