"""The networks of the global descriptors, built and filled in one place.

Tensors are ``[B, C, H, W]`` feature maps and ``[B, D]`` descriptors. Every model of the zoo
(NetVLAD, AP-GeM, DELG, the trainable ``gem`` / ``netvlad_head`` models) and every network
trained by `locretrieval.training` is a `RetrievalNet`: ``backbone -> pooling (GeM, GeM over a
spatial pyramid, NetVLAD, or a head of `locretrieval.models.trainable.heads`: MixVPR, SALAD, BoQ) -> optional
whitening (affine) -> L2``, plus an optional projection applied after multi-scale
aggregation (AP-GeM's PCA). A pooling is any module class built as ``cls(channels, **options)``
that sets ``output_dim``, chosen by ``_target_`` in ``configs/model/pooling/`` (`pooling_settings`).
`build_retrieval_net` builds one on a backbone (`locretrieval.models.trainable.backbones`, chosen the same way in
``configs/model/backbone/``) and `load_weights` fills it from a state dict and records where the
weights came from.
"""

from __future__ import annotations

import hashlib
import inspect
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from locretrieval.errors import DataFileError
from locretrieval.models.files.weights import content_sha256, plain
from locretrieval.moved import current_path
from locretrieval.parts import PartGroup, import_part

#: Guards divisions by the norm of all-zero vectors.
NORM_EPS = 1e-12
#: What ``model.pooling`` builds: a torch module whose ``output_dim`` is its descriptor's size.
POOLING = PartGroup((nn.Module,))


def l2_normalize(x: torch.Tensor, dim: int = -1) -> torch.Tensor:
    return F.normalize(x, p=2, dim=dim, eps=NORM_EPS)


class GeMPooling(nn.Module):
    """Generalised mean pooling ``(mean(clamp(x, eps)^p))^(1/p)`` over the spatial axes of a
    ``channels``-channel map (``output_dim = channels``).

    ``p`` is a parameter (learned when ``trainable``; DELG keeps it fixed). Computed in
    float32 even under autocast: ``x^p`` overflows float16 for activations above ~40.
    """

    #: Floor of the activations before the power.
    eps = 1e-6

    def __init__(self, channels: int, p: float, trainable: bool) -> None:
        super().__init__()
        self.p = nn.Parameter(torch.tensor([float(p)]), requires_grad=bool(trainable))
        self.output_dim = int(channels)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        with torch.autocast(features.device.type, enabled=False):
            x = features.float().clamp(min=self.eps).pow(self.p)
            return x.mean(dim=(2, 3)).pow(1.0 / self.p)


class SpatialPyramidGeM(GeMPooling):
    """GeM over a pyramid of image regions, concatenated: where things are in the image, not only
    what is seen (a pooling that keeps the layout and has no parameter but ``p``, so a pretrained
    trunk starts from GeM's descriptor, unlike a head that starts random).

    ``levels`` are ``(rows, cols)`` grids; each cell is GeM over its region
    (``adaptive_avg_pool2d`` of ``x^p``: regions overlap by a cell where the map does not divide).
    Each level's cells, flattened row-major (cells fastest, channels slowest: ``c * cells + i``), are
    L2-normalised together, so every level weighs the same in the final (unit) descriptor. The
    ``(1, 1)`` level alone is GeM up to a scale.
    """

    def __init__(self, channels: int, levels: Sequence[Sequence[int]], p: float, trainable: bool) -> None:
        super().__init__(channels, p, trainable)
        self.levels = tuple((int(rows), int(cols)) for rows, cols in levels)
        if not self.levels or any(rows < 1 or cols < 1 for rows, cols in self.levels):
            raise ValueError(f"gem_pyramid levels must be (rows, cols) grids of at least 1 x 1, got {levels!r}")
        self.output_dim = channels * sum(rows * cols for rows, cols in self.levels)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        with torch.autocast(features.device.type, enabled=False):
            x = features.float().clamp(min=self.eps).pow(self.p)
            blocks = [l2_normalize(F.adaptive_avg_pool2d(x, grid).pow(1.0 / self.p).flatten(1)) for grid in self.levels]
            return torch.cat(blocks, dim=1)


class NetVLADPooling(nn.Module):
    """NetVLAD (Arandjelovic et al., CVPR 2016) with input L2 ("preL2") and intra-normalisation.

    Soft-assignment ``softmax_k(w_k . x_n)`` (no bias, as in the authors' model) over ``clusters``
    centres ``c_k`` (``[K, D]``), residual sums ``V[k] = sum_n a_kn (x_n - c_k)``, each ``V[k]``
    L2-normalised, then the whole vector. The output is flattened cluster-fastest (index
    ``d * K + k``), which is MATLAB's column-major flattening of the ``K x D`` VLAD matrix of the
    authors' code, so the released whitening matrices apply unchanged.
    """

    def __init__(self, channels: int, clusters: int) -> None:
        super().__init__()
        self.dim, self.clusters = int(channels), int(clusters)
        self.assignment = nn.Conv2d(self.dim, self.clusters, kernel_size=1, bias=False)
        self.centers = nn.Parameter(torch.empty(self.clusters, self.dim))
        nn.init.normal_(self.centers, std=self.dim**-0.5)

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
    import torchvision  # here: importing it costs more than a second, and only these backbones need it

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


def pooling_settings(pooling: Callable[..., nn.Module] | Mapping[str, Any]) -> dict[str, Any]:
    """A pooling as an architecture records it: ``{"_target_": "<module>.<class>", option: value}``,
    every option of the class's signature but ``channels``.

    ``pooling`` is what Hydra builds from a ``model/pooling`` config (``_partial_: true``: the class
    with its options, given the trunk's ``channels`` later), the class itself, or these settings.
    A pooling is any ``nn.Module`` class built as ``cls(channels, **options)`` that sets
    ``output_dim``; options it does not take, or lacks, are refused here, naming them."""
    if isinstance(pooling, Mapping):
        options = {key: value for key, value in pooling.items() if key != "_partial_"}
        target = options.pop("_target_", None)
        if target is None:
            raise ValueError(f"model.pooling has no _target_ (choose one: model/pooling=gem): {options}")
        target = current_path(str(target))  # a module path before 0.12 recorded as today's
        cls = import_part(target, "model.pooling", POOLING)
    else:
        cls = pooling.func if isinstance(pooling, partial) else pooling
        options = dict(pooling.keywords) if isinstance(pooling, partial) else {}
        if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
            raise ValueError(f"model.pooling must name an nn.Module class, got {pooling!r}")
        target = f"{cls.__module__}.{cls.__qualname__}"
    try:
        bound = inspect.signature(cls).bind(0, **options)
    except TypeError as error:
        raise ValueError(f"model.pooling ({target}): {error}; it takes {pooling_options(cls)}") from error
    bound.apply_defaults()
    arguments = dict(bound.arguments)
    arguments.pop(next(iter(inspect.signature(cls).parameters)))  # channels: the trunk's
    return {"_target_": str(target), **plain(arguments)}


def pooling_options(cls: type[nn.Module]) -> list[str]:
    """The options a pooling class takes (all its parameters but the first, ``channels``)."""
    return list(inspect.signature(cls).parameters)[1:]


#: How 0.11.0 and earlier recorded a pooling: ``{type: <name>, options as configured}``, the heads'
#: other options at these values (their defaults then). `upgrade_legacy_pooling` reads such records.
LEGACY_POOLINGS: dict[str, tuple[str, dict[str, Any]]] = {
    "gem": ("locretrieval.models.networks.GeMPooling", {}),
    "gem_pyramid": ("locretrieval.models.networks.SpatialPyramidGeM", {"levels": [[1, 1], [1, 3]]}),
    "netvlad": ("locretrieval.models.networks.NetVLADPooling", {}),
    "mixvpr": (
        "locretrieval.models.trainable.heads.MixVPRHead",
        {"grid": [7, 7], "blocks": 4, "mlp_ratio": 1, "out_channels": 256, "out_rows": 4},
    ),
    "salad": (
        "locretrieval.models.trainable.heads.SALADHead",
        {
            "clusters": 16,
            "cluster_dim": 32,
            "token_dim": 64,
            "hidden": 256,
            "iterations": 3,
            "regularization": 1.0,
            "token": "mean",
            "dropout": 0.0,
        },
    ),
    "boq": (
        "locretrieval.models.trainable.heads.BoQHead",
        {"dim": 128, "queries": 16, "blocks": 2, "heads": 4, "rows": 8, "input_kernel": 1},
    ),
}


def upgrade_legacy_pooling(settings: Mapping[str, Any]) -> dict[str, Any]:
    """A pooling record of a checkpoint in today's form (`pooling_settings`): a ``{type: ...}`` record
    of 0.11.0 or earlier becomes its class's settings (options of other types, which were ignored
    then, left out); a record with ``_target_`` is returned as it is."""
    if "_target_" in settings:
        return dict(settings)
    if settings.get("type") not in LEGACY_POOLINGS:
        raise ValueError(f"a pooling record of unknown type {settings.get('type')!r}: {dict(settings)}")
    target, defaults = LEGACY_POOLINGS[settings["type"]]
    taken = pooling_options(import_part(target, "model.pooling", POOLING))
    return {"_target_": target, **defaults, **{key: value for key, value in settings.items() if key in taken}}


def build_pooling(channels: int, settings: Mapping[str, Any]) -> nn.Module:
    """The pooling of ``settings`` (`pooling_settings`) on a ``channels``-channel map, randomly initialised."""
    options = dict(settings)
    module = import_part(current_path(str(options.pop("_target_", None))), "model.pooling", POOLING)(
        channels, **options
    )
    if not isinstance(getattr(module, "output_dim", None), int):
        raise ValueError(f"model.pooling ({settings['_target_']}) must set output_dim, its descriptor's size")
    return module


def build_retrieval_net(
    backbone: Any, pooling: Mapping[str, Any], whiten_dim: int | None = None, projection_dim: int | None = None
) -> RetrievalNet:
    """The pooling of the settings ``pooling`` (`pooling_settings`) on the trunk ``backbone`` builds
    (a `locretrieval.models.trainable.backbones.Backbone`), optional FC whitening to ``whiten_dim`` and final
    projection to ``projection_dim`` (applied after multi-scale aggregation), randomly initialised."""
    if pooling.get("token") == "class":
        raise ValueError(f"pooling token: class needs a trunk with a class token (model=dinov2), not {backbone!r}")
    trunk, channels = backbone.build()
    module = build_pooling(channels, pooling)
    pooled_dim = module.output_dim
    whitening = nn.Linear(pooled_dim, whiten_dim) if whiten_dim else None
    projection = nn.Linear(whiten_dim or pooled_dim, projection_dim) if projection_dim else None
    return RetrievalNet(trunk, module, pooled_dim, whitening, projection)


@dataclass(frozen=True)
class WeightsInfo:
    """Where the parameters came from: the weight file's SHA-256 (``None`` without a file) and
    the parameters left randomly initialised, with the seed."""

    sha256: str | None
    random_parameters: tuple[str, ...] = ()
    seed: int | None = None

    @property
    def random_init(self) -> bool:
        return bool(self.random_parameters)

    def identity(self) -> dict[str, Any]:
        return {
            "sha256": self.sha256,
            "random_parameters": list(self.random_parameters),
            "seed": self.seed if self.random_init else None,
        }


def load_weights(
    factory: Callable[[], RetrievalNet],
    state_dict: Mapping[str, torch.Tensor] | None,
    path: str | Path | None,
    random_init: bool = False,
    seed: int = 0,
) -> tuple[RetrievalNet, WeightsInfo]:
    """The network ``factory`` builds, filled with ``state_dict`` (read from the file ``path``),
    and what the weights came from.

    Without ``random_init`` every parameter must come from ``state_dict`` (the network is
    built empty, then filled: fast even for VGG16's 134M-parameter whitening). With it, the
    network is built with the seeded default initialisation and ``state_dict`` (if any)
    overrides what it holds; the parameters it lacks are listed in the `WeightsInfo`. Names
    in ``state_dict`` the network has no place for are always an error naming ``path``.

    The network's shapes are compared with ``state_dict``'s before any of it is allocated (built
    on the ``meta`` device first, `check_shapes`): sizes a weight file's architecture declares
    (``whiten_dim`` 600,000 in a 2 KB checkpoint asked for 3 GB) must be those its weights have.
    """
    source = str(path) if path is not None else "no weight file"
    if not random_init and state_dict is None:
        raise ValueError(f"{source}: no weights to load; set model.random_init=true for random weights")
    if state_dict is not None:
        with torch.device("meta"):
            skeleton = factory()
        check_shapes(skeleton, state_dict, source, complete=not random_init)
    if not random_init:
        network = skeleton
        network.to_empty(device="cpu")
        for name, buffer in network.named_buffers():
            if name.endswith("num_batches_tracked"):
                buffer.zero_()
        _load(network, state_dict, source)
        random_parameters: tuple[str, ...] = ()
    else:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            network = factory()
        if state_dict is None:
            random_parameters = tuple(name for name, _ in network.named_parameters())
        else:
            random_parameters = tuple(_load(network, state_dict, source))
    sha256 = content_sha256(path) if path is not None else None
    return network, WeightsInfo(sha256, random_parameters, int(seed))


def check_shapes(network: nn.Module, state_dict: Mapping[str, torch.Tensor], source: str, complete: bool) -> None:
    """Raise a `DataFileError` naming ``source`` when a value of ``state_dict`` has no place in
    ``network`` (built on the ``meta`` device: nothing allocated) or another shape than its place
    there, or (``complete``) when a parameter of the network has no value in it."""
    places = network.state_dict()
    unexpected = [name for name in state_dict if name not in places]
    if unexpected:
        raise DataFileError(
            source, f"holds {len(unexpected)} values the network has no place for, e.g. {unexpected[:6]}"
        )
    for name, value in state_dict.items():
        if not isinstance(value, torch.Tensor):
            raise DataFileError(source, f"{name} holds {type(value).__name__}, not a tensor")
        if tuple(value.shape) != tuple(places[name].shape):
            raise DataFileError(
                source,
                f"does not fit the network its architecture describes: {name} has shape {tuple(value.shape)} in "
                f"the file, {tuple(places[name].shape)} in the network (compared before the network is allocated)",
            )
    missing = [name for name in places if name not in state_dict and not name.endswith("num_batches_tracked")]
    if complete and missing:
        raise DataFileError(
            source,
            f"holds no values for {len(missing)} parameters, e.g. {missing[:6]}; set model.random_init=true to "
            "initialise them randomly",
        )


def _load(network: RetrievalNet, state_dict: Mapping[str, torch.Tensor], source: str) -> list[str]:
    """Load ``state_dict`` (its names and shapes checked: `check_shapes`); return the parameters it lacks."""
    try:
        result = network.load_state_dict(dict(state_dict), strict=False)
    except RuntimeError as error:
        raise ValueError(f"{source}: does not fit the network: {error}") from error
    return [name for name in result.missing_keys if not name.endswith("num_batches_tracked")]


def state_sha256(network: nn.Module) -> str:
    """SHA-256 of a network's state dict (names, dtypes, shapes and values, in order): changes
    whenever a parameter or buffer does, in memory or on disk."""
    digest = hashlib.sha256()
    for name, tensor in network.state_dict().items():
        values = tensor.detach().to("cpu").contiguous()
        digest.update(f"{name}|{values.dtype}|{tuple(values.shape)}\n".encode())
        digest.update(values.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()
