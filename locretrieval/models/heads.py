"""Network pieces of the global descriptors: backbones, GeM and NetVLAD pooling, `RetrievalNet`.

Tensors are ``[B, C, H, W]`` feature maps and ``[B, D]`` descriptors. Every model of the zoo
(NetVLAD, AP-GeM, DELG, the trainable ``gem`` / ``netvlad_head`` models) is a `RetrievalNet`:
``backbone -> pooling -> optional whitening (affine) -> L2``, plus an optional projection
applied after multi-scale aggregation (AP-GeM's PCA).
"""

from __future__ import annotations

from collections import OrderedDict

import torch
import torch.nn.functional as F
import torchvision
from torch import nn

#: Guards divisions by the norm of all-zero vectors.
NORM_EPS = 1e-12


def l2_normalize(x: torch.Tensor, dim: int = -1) -> torch.Tensor:
    return F.normalize(x, p=2, dim=dim, eps=NORM_EPS)


class GeMPooling(nn.Module):
    """Generalised mean pooling ``(mean(clamp(x, eps)^p))^(1/p)`` over the spatial axes.

    ``p`` is a parameter (learned when ``trainable``; DELG keeps it fixed). Computed in
    float32 even under autocast: ``x^p`` overflows float16 for activations above ~40.
    """

    def __init__(self, p: float = 3.0, trainable: bool = True, eps: float = 1e-6) -> None:
        super().__init__()
        self.p = nn.Parameter(torch.tensor([float(p)]), requires_grad=trainable)
        self.eps = eps

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        with torch.autocast(features.device.type, enabled=False):
            x = features.float().clamp(min=self.eps).pow(self.p)
            return x.mean(dim=(2, 3)).pow(1.0 / self.p)


class NetVLADPooling(nn.Module):
    """NetVLAD (Arandjelovic et al., CVPR 2016) with input L2 ("preL2") and intra-normalisation.

    Soft-assignment ``softmax_k(w_k . x_n)`` (no bias, as in the authors' model) over ``clusters``
    centres ``c_k`` (``[K, D]``), residual sums ``V[k] = sum_n a_kn (x_n - c_k)``, each ``V[k]``
    L2-normalised, then the whole vector. The output is flattened cluster-fastest (index
    ``d * K + k``), which is MATLAB's column-major flattening of the ``K x D`` VLAD matrix of the
    authors' code, so the released whitening matrices apply unchanged.
    """

    def __init__(self, dim: int, clusters: int) -> None:
        super().__init__()
        self.dim, self.clusters = dim, clusters
        self.assignment = nn.Conv2d(dim, clusters, kernel_size=1, bias=False)
        self.centers = nn.Parameter(torch.empty(clusters, dim))
        nn.init.normal_(self.centers, std=dim**-0.5)

    @property
    def output_dim(self) -> int:
        return self.dim * self.clusters

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        with torch.autocast(features.device.type, enabled=False):
            x = l2_normalize(features.float(), dim=1)
            soft = torch.softmax(self.assignment(x).flatten(2), dim=1)  # [B, K, N]
            x = x.flatten(2)  # [B, D, N]
            vlad = torch.einsum("bkn,bdn->bdk", soft, x) - self.centers.t()[None] * soft.sum(dim=2)[:, None, :]
            vlad = l2_normalize(vlad, dim=1)  # intra-normalisation, per cluster
            return l2_normalize(vlad.flatten(1), dim=1)


class RetrievalNet(nn.Module):
    """``backbone -> pooling -> whitening -> L2`` per scale; ``finalize`` applies ``projection``.

    ``forward(images)`` takes normalised ``[B, 3, H, W]`` images and returns unit ``[B, D]``
    descriptors of one scale. The extraction engine sums them over scales, L2-normalises, and
    calls ``finalize`` (``projection`` then L2, or the identity without one).
    """

    def __init__(
        self,
        backbone: nn.Module,
        pooling: nn.Module,
        pooled_dim: int,
        whitening: nn.Linear | None = None,
        projection: nn.Linear | None = None,
    ) -> None:
        super().__init__()
        self.backbone = backbone
        self.pooling = pooling
        self.whitening = whitening
        self.projection = projection
        dim = whitening.out_features if whitening is not None else pooled_dim
        self.output_dim = projection.out_features if projection is not None else dim

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        pooled = self.pooling(self.backbone(images))
        if self.whitening is not None:
            pooled = self.whitening(pooled)
        return l2_normalize(pooled.float())

    def finalize(self, descriptors: torch.Tensor) -> torch.Tensor:
        if self.projection is None:
            return descriptors
        return l2_normalize(self.projection(descriptors))


def torchvision_trunk(name: str) -> tuple[nn.Module, int]:
    """The convolutional trunk of a torchvision classifier and its output channels.

    Parameter names equal torchvision's (``conv1.weight``, ``layer1.0.bn1.weight``,
    ``features.0.weight``), so torchvision checkpoints load with a ``backbone.`` prefix.
    ResNets stop after ``layer4``; VGGs at conv5_3 without its ReLU and the last max-pool
    (NetVLAD's cut); other models at their ``features`` module. Built with torchvision's random
    initialisation on the default device (``with torch.device("meta")`` builds it empty).
    """
    try:
        model = torchvision.models.get_model(name, weights=None)
    except ValueError as error:
        raise ValueError(f"unknown torchvision backbone {name!r}: {error}") from error
    if name.startswith(("resnet", "resnext", "wide_resnet")):
        children = [(key, module) for key, module in model.named_children() if key not in ("avgpool", "fc")]
        trunk = nn.Sequential(OrderedDict(children))
    elif name.startswith("vgg"):
        features = model.features
        cut = len(features) - 2  # drop the final ReLU and max-pool
        trunk = nn.Sequential(OrderedDict(features=nn.Sequential(*list(features)[:cut])))
    elif hasattr(model, "features"):
        trunk = nn.Sequential(OrderedDict(features=model.features))
    else:
        raise ValueError(f"torchvision model {name!r} has no convolutional trunk this code knows how to cut")
    return trunk, trunk_channels(trunk)


def trunk_channels(trunk: nn.Module) -> int:
    """Output channels of a convolutional trunk (one tiny forward pass, shape-only on meta)."""
    device = next(trunk.parameters()).device
    with torch.no_grad():
        return int(trunk.eval()(torch.zeros(1, 3, 64, 64, device=device)).shape[1])
