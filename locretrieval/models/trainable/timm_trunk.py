"""timm models as feature trunks (``model.backbone=timm:<name>``, and EfficientNet-Lite0)."""

from __future__ import annotations

import torch
from torch import nn

#: Backbone names ``timm:<model>`` select a timm model.
TIMM_PREFIX = "timm:"


class TimmTrunk(nn.Module):
    """The feature map of a timm model (built without classifier and pooling, random weights):
    a ConvNet's ``forward_features`` ``[B, C, H, W]``; a ViT's patch tokens (its prefix tokens,
    class and registers, dropped) as a ``[B, C, H / patch, W / patch]`` map (rounded up: the input
    is padded to the patch grid, ``dynamic_img_size`` and ``dynamic_img_pad``). Parameters are the timm model's,
    under ``timm.``."""

    def __init__(self, name: str) -> None:
        super().__init__()
        import timm

        try:  # a ViT takes any size, padded to its patch grid
            self.timm = timm.create_model(
                name, pretrained=False, num_classes=0, global_pool="", dynamic_img_size=True, dynamic_img_pad=True
            )
        except TypeError:  # not a ViT: no dynamic image size to set
            self.timm = timm.create_model(name, pretrained=False, num_classes=0, global_pool="")
        except RuntimeError as error:
            raise ValueError(f"unknown timm backbone {name!r}: {error}") from error
        self.channels = int(self.timm.num_features)
        self.patch = getattr(getattr(self.timm, "patch_embed", None), "patch_size", None)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        features = self.timm.forward_features(images)
        if features.ndim == 4:  # channels last for some (Swin: output_fmt NHWC)
            return (
                features.permute(0, 3, 1, 2)
                if str(getattr(self.timm, "output_fmt", "NCHW")).endswith("NHWC")
                else features
            )
        tokens = features[:, self.timm.num_prefix_tokens :]
        height, width = -(-images.shape[2] // self.patch[0]), -(-images.shape[3] // self.patch[1])  # the padded grid
        return tokens.transpose(1, 2).reshape(len(tokens), self.channels, height, width)
