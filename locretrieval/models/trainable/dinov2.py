"""DINOv2 and the place-recognition heads published on it (SALAD, BoQ, MegaLoc), built from
locretrieval's parts and filled from their authors' weight files through a key mapping, so that
they are benchmarked and fine-tuned (``train.py finetune=salad``) like any trainable model.

- `DinoV2Trunk`: timm's ViT of the same parameters (``vit_base_patch14_dinov2``), run as DINOv2's
  own code runs it (`dinov2_position_embedding`), with the final LayerNorm optional (BoQ reads the
  last block's output) and the class token returned beside the map when a head uses it (SALAD,
  MegaLoc).
- `DinoV2Descriptor`: a head of `locretrieval.models.trainable.heads` (or GeM) on that trunk; its weights are
  our checkpoint or DINOv2's published backbone file (the head then needs ``random_init``).
  `SALADDescriptor`, `BoQDescriptor` and `MegaLocDescriptor` read their authors' released file
  whole: each `KeyMapping` renames every key to its place here, and refuses a file with keys it
  does not know.

Written from the authors' code (github.com/facebookresearch/dinov2, serizba/salad,
amaralibey/Bag-of-Queries, gmberton/MegaLoc); nothing of theirs is imported or downloaded.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from locretrieval.models.extraction import IMAGENET_MEAN, IMAGENET_STD, ExtractionSettings
from locretrieval.models.files.weights import Weights, WeightSource
from locretrieval.models.networks import RetrievalNet, build_pooling, upgrade_legacy_pooling
from locretrieval.models.trainable import TrainableDescriptor
from locretrieval.models.trainable.backbones import Normalization

#: DINOv2's patch side in pixels: every image side is a multiple of it.
PATCH = 14
#: DINOv2's offset of the interpolation scale factor (its ``interpolate_offset``).
POSITION_OFFSET = 0.1


def dinov2_position_embedding(
    embedding: torch.Tensor, rows: int, cols: int, offset: float = POSITION_OFFSET
) -> torch.Tensor:
    """DINOv2's position embedding ``[1, 1 + rows * cols, C]`` for a ``rows x cols`` patch grid from
    the stored ``[1, 1 + S * S, C]`` (class position first, kept): the ``S x S`` grid resized
    bicubically by the scale factors ``((rows + offset) / S, (cols + offset) / S)`` without
    antialiasing, in float32, as DINOv2's ``interpolate_pos_encoding`` (the stored grid itself
    for a square input of ``S x S`` patches). Written here because timm resamples to the size with
    antialiasing, which gives other values than the ones the published heads were trained on."""
    class_position, grid = embedding[:, :1], embedding[:, 1:]
    side = math.isqrt(grid.shape[1])
    if rows == cols == side:
        return embedding
    channels = grid.shape[2]
    grid = grid.float().reshape(1, side, side, channels).permute(0, 3, 1, 2)
    scale = ((rows + offset) / side, (cols + offset) / side)
    grid = F.interpolate(grid, scale_factor=scale, mode="bicubic", align_corners=False)
    if tuple(grid.shape[2:]) != (rows, cols):  # the offset guards the floor of size * scale
        raise RuntimeError(f"position grid resized to {tuple(grid.shape[2:])}, not {(rows, cols)}")
    grid = grid.permute(0, 2, 3, 1).reshape(1, rows * cols, channels).to(embedding.dtype)
    return torch.cat([class_position, grid], dim=1)


class DinoV2Trunk(nn.Module):
    """A DINOv2 ViT (a timm ``vit_*_patch14_dinov2`` model, random weights, parameters under
    ``timm.`` named as in DINOv2's checkpoints) mapping ``[B, 3, H, W]`` images, sides multiples
    of `PATCH`, to the patch tokens as a map ``[B, C, H / 14, W / 14]`` (row-major), and with
    ``class_token`` also the class token ``[B, C]``; both after the final LayerNorm when
    ``final_norm``."""

    def __init__(self, name: str, class_token: bool = False, final_norm: bool = True) -> None:
        super().__init__()
        import timm

        if "dinov2" not in name:
            raise ValueError(f"a DINOv2 trunk is a timm vit_*_patch14_dinov2 model, not {name!r}")
        try:
            self.timm = timm.create_model(name, pretrained=False, num_classes=0, global_pool="", dynamic_img_size=True)
        except RuntimeError as error:
            raise ValueError(f"unknown timm model {name!r}: {error}") from error
        if self.timm.num_prefix_tokens != 1:
            raise ValueError(f"{name}: DINOv2 with registers is not supported (its tokens are laid out differently)")
        self.channels = int(self.timm.num_features)
        self.class_token, self.final_norm = bool(class_token), bool(final_norm)

    def forward(self, images: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        batch, _, height, width = images.shape
        if height % PATCH or width % PATCH:
            raise ValueError(f"DINOv2 takes image sides that are multiples of {PATCH} px, got {width} x {height}")
        rows, cols = height // PATCH, width // PATCH
        vit = self.timm
        patches = vit.patch_embed(images).reshape(batch, rows * cols, self.channels)
        tokens = torch.cat([vit.cls_token.expand(batch, -1, -1), patches], dim=1)
        tokens = vit.blocks(tokens + dinov2_position_embedding(vit.pos_embed, rows, cols))
        if self.final_norm:
            tokens = vit.norm(tokens)
        feature_map = tokens[:, 1:].transpose(1, 2).reshape(batch, self.channels, rows, cols)
        return (feature_map, tokens[:, 0]) if self.class_token else feature_map


#: A tensor's conversion from the published layout to ours.
Transform = Callable[[torch.Tensor], torch.Tensor]


def squeeze_pointwise(weight: torch.Tensor) -> torch.Tensor:
    """A 1 x 1 convolution's ``[out, in, 1, 1]`` weight as a linear layer's ``[out, in]``."""
    return weight[:, :, 0, 0] if weight.ndim == 4 else weight


@dataclass(frozen=True)
class KeyMapping:
    """The authors' key names -> ours: ``rules`` are ``(regular expression, replacement,
    transform or None)``, the first that matches a whole key renames it; keys matching
    ``dropped`` have no place here on purpose (DINOv2's ``mask_token``, used only in its
    pre-training). Any other key is an error: the file is not of this layout."""

    layout: str
    rules: tuple[tuple[str, str, Transform | None], ...]
    dropped: str = r"(.*\.)?mask_token"

    def apply(self, state: Mapping[str, torch.Tensor], path: Path) -> dict[str, torch.Tensor]:
        mapped, unknown = {}, []
        for key, value in state.items():
            if re.fullmatch(self.dropped, key):
                continue
            for pattern, replacement, transform in self.rules:
                if match := re.fullmatch(pattern, key):
                    mapped[match.expand(replacement)] = transform(value) if transform else value
                    break
            else:
                unknown.append(key)
        if unknown:
            raise ValueError(
                f"{path}: not a {self.layout} weight file: {len(unknown)} keys this layout has no place for, "
                f"e.g. {unknown[:6]}"
            )
        return mapped


#: DINOv2's released backbone (``dinov2_vitb14_pretrain.pth``): its keys are timm's.
DINOV2 = KeyMapping("DINOv2", ((r"(.*)", r"backbone.timm.\1", None),))


def salad_rules(prefix: str) -> tuple[tuple[str, str, Transform | None], ...]:
    """SALAD's aggregator under ``prefix``: ``score`` and ``cluster_features`` are 1 x 1
    convolutions with dropout at index 1 (their second layer at 3), ``token_features`` linear."""
    prefix = re.escape(prefix)
    return (
        (rf"{prefix}score\.0\.(weight|bias)", r"pooling.scores.0.\1", squeeze_pointwise),
        (rf"{prefix}score\.3\.(weight|bias)", r"pooling.scores.2.\1", squeeze_pointwise),
        (rf"{prefix}cluster_features\.0\.(weight|bias)", r"pooling.features.0.\1", squeeze_pointwise),
        (rf"{prefix}cluster_features\.3\.(weight|bias)", r"pooling.features.2.\1", squeeze_pointwise),
        (rf"{prefix}token_features\.([02])\.(weight|bias)", r"pooling.token.\1.\2", None),
        (rf"{prefix}dust_bin", r"pooling.dustbin", None),
    )


#: ``dino_salad.ckpt``: DINOv2 under ``backbone.model.``, SALAD under ``aggregator.``.
SALAD = KeyMapping("SALAD", ((r"backbone\.model\.(.*)", r"backbone.timm.\1", None), *salad_rules("aggregator.")))

#: ``dinov2_12288.pth``: DINOv2 under ``backbone.dino.``, BoQ under ``aggregator.`` (``proj_c`` a
#: 3 x 3 convolution, ``boqs.<i>`` the blocks, ``fc`` the row projection).
BOQ = KeyMapping(
    "BoQ",
    (
        (r"backbone\.dino\.(.*)", r"backbone.timm.\1", None),
        (r"aggregator\.proj_c\.(.*)", r"pooling.input_projection.\1", None),
        (r"aggregator\.norm_input\.(.*)", r"pooling.input_norm.\1", None),
        (r"aggregator\.boqs\.(\d+)\.encoder\.(.*)", r"pooling.encoders.\1.\2", None),
        (r"aggregator\.boqs\.(\d+)\.queries", r"pooling.queries.\1", None),
        (r"aggregator\.boqs\.(\d+)\.self_attn\.(.*)", r"pooling.query_attention.\1.\2", None),
        (r"aggregator\.boqs\.(\d+)\.norm_q\.(.*)", r"pooling.query_norms.\1.\2", None),
        (r"aggregator\.boqs\.(\d+)\.cross_attn\.(.*)", r"pooling.cross_attention.\1.\2", None),
        (r"aggregator\.boqs\.(\d+)\.norm_out\.(.*)", r"pooling.output_norms.\1.\2", None),
        (r"aggregator\.fc\.(.*)", r"pooling.row_projection.\1", None),
    ),
)


def salad_columns(clusters: int, cluster_dim: int, token_dim: int) -> torch.Tensor:
    """For each dimension of our SALAD descriptor, the published one holding the same value:
    the token first in both; then ours is cluster-major (``k * cluster_dim + d``), the
    published dimension-major (``d * clusters + k``)."""
    aggregated = torch.arange(clusters * cluster_dim).reshape(cluster_dim, clusters).t().reshape(-1)
    return torch.cat([torch.arange(token_dim), token_dim + aggregated])


class DinoV2Descriptor(TrainableDescriptor):
    """``pooling`` (a head of `locretrieval.models.trainable.heads`, or GeM) on a DINOv2 ``backbone`` (a timm
    ``vit_*_patch14_dinov2`` name), the final LayerNorm when ``final_norm``, optional whitening
    to ``whiten_dim``; images resized to ``size`` (``[width, height]``, or shrunk to
    ``max_side``), sides rounded to multiples of 14, normalised with ImageNet's mean and std.
    Weights: our checkpoint, or the authors' file of ``mapping`` (`KeyMapping`)."""

    model = "dinov2"
    multiple_of = PATCH
    mapping = DINOV2
    source = WeightSource(
        "dinov2_vitb14_pretrain.pth (DINOv2's ViT-B/14; the head then needs model.random_init=true)",
        "Meta publishes it at https://dl.fbaipublicfiles.com/dinov2/dinov2_vitb14/dinov2_vitb14_pretrain.pth "
        "(github.com/facebookresearch/dinov2)",
    )

    def __init__(
        self,
        name: str,
        backbone: str,
        final_norm: bool,
        pooling: Callable[..., nn.Module] | Mapping[str, Any],
        whiten_dim: int | None,
        weights: str | None,
        random_init: bool,
        seed: int,
        size: Sequence[int] | str | None,
        max_side: int | str | None,
        scales: Sequence[float] | str,
        extraction: ExtractionSettings | Mapping[str, Any],
    ) -> None:
        self.final_norm = bool(final_norm)
        super().__init__(
            name, backbone, pooling, whiten_dim, weights, random_init, seed, max_side, scales, extraction, size
        )

    def architecture_of(self, backbone: Any, pooling: dict[str, Any], whiten_dim: int | None) -> dict[str, Any]:
        """The timm ViT's name as ``backbone`` (DINOv2's own trunk, `DinoV2Trunk`), and ``final_norm``."""
        return {"backbone": str(backbone), "pooling": pooling, "whiten_dim": whiten_dim, "final_norm": self.final_norm}

    def upgrade_architecture(self, stored: Mapping[str, Any]) -> dict[str, Any]:
        return {**stored, "pooling": upgrade_legacy_pooling(stored["pooling"])}

    def input_normalization(self, architecture: Mapping[str, Any]) -> Normalization:
        """ImageNet's mean and std, as DINOv2 and the descriptors built on it."""
        return IMAGENET_MEAN, IMAGENET_STD

    def build_network(self, architecture: Mapping[str, Any]) -> RetrievalNet:
        pooling = architecture["pooling"]
        trunk = DinoV2Trunk(
            architecture["backbone"], class_token=pooling.get("token") == "class", final_norm=architecture["final_norm"]
        )
        head = build_pooling(trunk.channels, pooling)
        whiten_dim = architecture["whiten_dim"]
        return RetrievalNet(
            trunk, head, head.output_dim, nn.Linear(head.output_dim, whiten_dim) if whiten_dim else None
        )

    def weight_source(self, architecture: Mapping[str, Any]) -> WeightSource:
        return self.source

    def key_mapping(self, architecture: Mapping[str, Any]) -> KeyMapping:
        """How the authors' file of this model is laid out."""
        return self.mapping

    def authors_weights(self, path: Path, content: Any, architecture: Mapping[str, Any]) -> Weights:
        mapping = self.key_mapping(architecture)
        state = content.get("state_dict", content) if isinstance(content, Mapping) else content
        if not (isinstance(state, Mapping) and state and all(isinstance(v, torch.Tensor) for v in state.values())):
            raise ValueError(f"{path}: neither a {mapping.layout} state dict nor a locretrieval checkpoint")
        return Weights(mapping.apply(state, path))


class SALADDescriptor(DinoV2Descriptor):
    """SALAD (Izquierdo and Civera, CVPR 2024) from ``dino_salad.ckpt``: DINOv2 ViT-B/14 and SALAD
    (64 clusters of 128, a 256-D class-token summary: 8448-D)."""

    model = "salad"
    mapping = SALAD
    source = WeightSource(
        "dino_salad.ckpt (SALAD: DINOv2 ViT-B/14 + SALAD)",
        "Izquierdo and Civera publish it at https://github.com/serizba/salad/releases/download/v1.0.0/dino_salad.ckpt",
    )


class BoQDescriptor(DinoV2Descriptor):
    """BoQ (Ali-bey et al., CVPR 2024) from ``dinov2_12288.pth``: DINOv2 ViT-B/14 without its final
    norm and Bag-of-Queries (a 3 x 3 projection to 384, 2 blocks of 64 queries, 32 rows: 12288-D)."""

    model = "boq"
    mapping = BOQ
    source = WeightSource(
        "dinov2_12288.pth (BoQ: DINOv2 ViT-B/14 + Bag-of-Queries)",
        "Ali-bey et al. publish it at "
        "https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/dinov2_12288.pth",
    )


class MegaLocDescriptor(DinoV2Descriptor):
    """MegaLoc (Berton and Masone, 2025) from ``megaloc.torch``: DINOv2 ViT-B/14, SALAD (64 clusters
    of 256, 256-D token: 16640-D) and a linear layer to 8448-D (here the whitening)."""

    model = "megaloc"
    source = WeightSource(
        "megaloc.torch (MegaLoc: DINOv2 ViT-B/14 + SALAD + a linear layer)",
        "Berton and Masone publish it at https://github.com/gmberton/MegaLoc/releases/download/v1.0/megaloc.torch",
    )

    def key_mapping(self, architecture: Mapping[str, Any]) -> KeyMapping:
        """DINOv2 under ``backbone.model.`` (or ``backbone.``), SALAD under ``aggregator.agg.``, the
        linear layer ``aggregator.linear`` with its input columns in our SALAD order."""
        pooling = architecture["pooling"]
        columns = salad_columns(int(pooling["clusters"]), int(pooling["cluster_dim"]), int(pooling["token_dim"]))
        return KeyMapping(
            "MegaLoc",
            (
                (r"backbone\.(?:model\.)?(.*)", r"backbone.timm.\1", None),
                *salad_rules("aggregator.agg."),
                (r"aggregator\.linear\.weight", r"whitening.weight", lambda weight: weight[:, columns]),
                (r"aggregator\.linear\.bias", r"whitening.bias", None),
            ),
        )
