"""Aggregation heads of today's place-recognition descriptors, written from their papers'
equations; each maps a trunk's feature map ``[B, C, H, W]`` to a unit descriptor ``[B, D]``.

- `MixVPRHead` (Ali-bey et al., WACV 2023): the map pooled to a fixed ``grid``, its
  ``H x W`` positions mixed by residual MLPs (one per block, shared across channels), then
  projected along channels (``C -> out_channels``) and positions (``H W -> out_rows``).
- `SALADHead` (Izquierdo and Civera, CVPR 2024): each local feature's affinity to ``clusters``
  learned centres plus a learned dustbin, turned into an assignment by optimal transport
  (log-domain Sinkhorn); the assigned, reduced features are summed per cluster,
  intra-normalised, and concatenated with a projected global token: the mean feature
  (convolutional trunks have no class token) or, as published on DINOv2, the class token.
- `BoQHead` (Ali-bey et al., CVPR 2024): ``blocks`` of a transformer encoder layer over the
  local features and learned queries that attend to themselves, then to the features
  (cross-attention); the queries' outputs of every block are projected along queries
  (``-> rows``) and flattened.

A trunk that also returns its class token gives ``(map, class token [B, C])`` (`dinov2.DinoV2Trunk`);
a head that has no use for it takes the map. The options of the published DINOv2 models (SALAD's
dropout, BoQ's 3 x 3 input convolution) are here so that their weights load unchanged
(`locretrieval.models.trainable.dinov2`). No head uses positions beyond the feature map's order:
SALAD and BoQ are invariant to a permutation of the local features, MixVPR to resampling the map
onto its grid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

#: A trunk's output: the feature map ``[B, C, H, W]``, or the map and the class token ``[B, C]``.
TrunkOutput = torch.Tensor | tuple[torch.Tensor, torch.Tensor]


def _mlp(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, outputs))


def feature_map(features: TrunkOutput) -> torch.Tensor:
    """The feature map of a trunk's output (its class token, if any, left out)."""
    return features[0] if isinstance(features, tuple) else features


class MixVPRHead(nn.Module):
    """Feature mixing: ``blocks`` residual MLPs ``x + W2 relu(W1 LN(x))`` over the ``grid``
    positions of each channel (hidden size ``mlp_ratio`` x positions), then
    ``out_channels x out_rows`` projections."""

    def __init__(
        self,
        channels: int,
        grid: Sequence[int],
        blocks: int,
        mlp_ratio: int,
        out_channels: int,
        out_rows: int,
    ) -> None:
        super().__init__()
        self.grid = tuple(int(side) for side in grid)
        positions = self.grid[0] * self.grid[1]
        self.norms = nn.ModuleList(nn.LayerNorm(positions) for _ in range(blocks))
        self.mixers = nn.ModuleList(_mlp(positions, positions * mlp_ratio, positions) for _ in range(blocks))
        self.channel_projection = nn.Linear(channels, out_channels)
        self.row_projection = nn.Linear(positions, out_rows)
        self.output_dim = out_channels * out_rows

    def forward(self, features: TrunkOutput) -> torch.Tensor:
        x = F.adaptive_avg_pool2d(feature_map(features), self.grid).flatten(2)  # [B, C, positions]
        for norm, mixer in zip(self.norms, self.mixers):
            x = x + mixer(norm(x))
        x = self.channel_projection(x.transpose(1, 2))  # [B, positions, out_channels]
        x = self.row_projection(x.transpose(1, 2))  # [B, out_channels, out_rows]
        return F.normalize(x.flatten(1), dim=1)


#: Where SALAD's global token comes from.
SALAD_TOKENS = ("mean", "class")


class SALADHead(nn.Module):
    """Optimal-transport aggregation with a dustbin: scores ``[clusters + 1, n]`` of the ``n``
    local features, transported with row marginals ``1 / (n + m)`` per cluster and
    ``(n - m) / (n + m)`` for the dustbin, column marginals ``1 / (n + m)`` per feature
    (`transport_plan`: ``iterations`` of log-domain Sinkhorn at temperature ``regularization``).
    ``token``: ``mean`` (the mean feature) or ``class`` (the trunk's class token, as published);
    ``dropout``: between the layers of the score and feature MLPs while training (published: 0.3).
    The aggregated part is flattened cluster-major (``k * cluster_dim + d``), the published
    code's is dimension-major: the same values in another order, so the same inner products."""

    def __init__(
        self,
        channels: int,
        clusters: int,
        cluster_dim: int,
        token_dim: int,
        hidden: int,
        iterations: int,
        regularization: float,
        token: str,
        dropout: float,
    ) -> None:
        super().__init__()
        if token not in SALAD_TOKENS:
            raise ValueError(f"SALAD token must be one of {list(SALAD_TOKENS)}, got {token!r}")
        self.clusters, self.iterations, self.regularization = clusters, iterations, regularization
        self.token_source, self.dropout = token, float(dropout)
        self.scores = _mlp(channels, hidden, clusters)
        self.features = _mlp(channels, hidden, cluster_dim)
        self.token = _mlp(channels, hidden, token_dim)
        self.dustbin = nn.Parameter(torch.tensor(1.0))
        self.output_dim = clusters * cluster_dim + token_dim

    def _branch(self, mlp: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
        """``mlp`` (linear, ReLU, linear) with dropout before its second layer."""
        return mlp[2](F.dropout(mlp[1](mlp[0](x)), self.dropout, self.training))

    def transport_plan(self, features: torch.Tensor) -> torch.Tensor:
        """``[B, clusters + 1, n]`` transport plan of the local features (last row: the dustbin)."""
        local = features.flatten(2).transpose(1, 2)  # [B, n, C]
        n, m = local.shape[1], self.clusters
        if n <= m:
            raise ValueError(
                f"SALAD needs more local features ({n} = H x W of the feature map) than clusters ({m}): "
                f"use larger images or fewer model.pooling.clusters"
            )
        scores = self._branch(self.scores, local).transpose(1, 2)  # [B, m, n]
        scores = torch.cat([scores, self.dustbin.expand(len(scores), 1, n)], dim=1) / self.regularization
        log_rows = torch.full((m + 1,), -math.log(n + m), device=scores.device, dtype=scores.dtype)
        log_rows[-1] = math.log(n - m) - math.log(n + m)
        log_columns = torch.full((n,), -math.log(n + m), device=scores.device, dtype=scores.dtype)
        u, v = torch.zeros_like(scores[:, :, 0]), torch.zeros_like(scores[:, 0, :])
        for _ in range(self.iterations):
            u = log_rows - torch.logsumexp(scores + v[:, None, :], dim=2)
            v = log_columns - torch.logsumexp(scores + u[:, :, None], dim=1)
        return torch.exp(scores + u[:, :, None] + v[:, None, :])

    def forward(self, features: TrunkOutput) -> torch.Tensor:
        if self.token_source == "class" and not isinstance(features, tuple):
            raise ValueError("SALAD with token: class needs a trunk that returns its class token (a DINOv2 trunk)")
        local = feature_map(features)
        with torch.autocast(local.device.type, enabled=False):
            local = local.float()
            n = local.shape[2] * local.shape[3]
            assignment = self.transport_plan(local)[:, : self.clusters] * (n + self.clusters)  # each feature's mass: 1
            reduced = self._branch(self.features, local.flatten(2).transpose(1, 2))  # [B, n, cluster_dim]
            aggregated = F.normalize(assignment @ reduced, dim=2).flatten(1)  # intra-normalised
            summary = features[1].float() if self.token_source == "class" else local.mean(dim=(2, 3))
            token = F.normalize(self.token(summary), dim=1)
            return F.normalize(torch.cat([token, aggregated], dim=1), dim=1)


class BoQHead(nn.Module):
    """Bag of learned queries: per block, a transformer encoder layer over the (projected)
    local features; ``queries`` learned queries with self-attention, then cross-attention to
    the features; every block's query outputs ``[blocks x queries, dim]`` projected to ``rows``.
    ``input_kernel``: the input projection's kernel on the map, 1 (a linear map per feature) or 3
    (a 3 x 3 convolution, as the published BoQ on ResNet and DINOv2)."""

    def __init__(
        self,
        channels: int,
        dim: int,
        queries: int,
        blocks: int,
        heads: int,
        rows: int,
        input_kernel: int,
    ) -> None:
        super().__init__()
        if input_kernel < 1 or input_kernel % 2 == 0:
            raise ValueError(f"BoQ input_kernel must be an odd positive size, got {input_kernel}")
        self.input_projection = (
            nn.Linear(channels, dim)
            if input_kernel == 1
            else nn.Conv2d(channels, dim, input_kernel, padding=input_kernel // 2)
        )
        self.input_norm = nn.LayerNorm(dim)
        self.encoders = nn.ModuleList(
            nn.TransformerEncoderLayer(
                dim, heads, dim_feedforward=4 * dim, dropout=0.0, batch_first=True, norm_first=False
            )
            for _ in range(blocks)
        )
        self.queries = nn.ParameterList(nn.Parameter(torch.randn(1, queries, dim) * dim**-0.5) for _ in range(blocks))
        self.query_attention = nn.ModuleList(nn.MultiheadAttention(dim, heads, batch_first=True) for _ in range(blocks))
        self.query_norms = nn.ModuleList(nn.LayerNorm(dim) for _ in range(blocks))
        self.cross_attention = nn.ModuleList(nn.MultiheadAttention(dim, heads, batch_first=True) for _ in range(blocks))
        self.output_norms = nn.ModuleList(nn.LayerNorm(dim) for _ in range(blocks))
        self.row_projection = nn.Linear(blocks * queries, rows)
        self.output_dim = dim * rows

    def forward(self, features: TrunkOutput) -> torch.Tensor:
        local = feature_map(features)
        if isinstance(self.input_projection, nn.Conv2d):
            x = self.input_projection(local).flatten(2).transpose(1, 2)
        else:
            x = self.input_projection(local.flatten(2).transpose(1, 2))
        x = self.input_norm(x)  # [B, n, dim]
        outputs = []
        for encoder, queries, attend, norm, cross, output_norm in zip(
            self.encoders, self.queries, self.query_attention, self.query_norms, self.cross_attention, self.output_norms
        ):
            x = encoder(x)
            q = queries.expand(len(x), -1, -1)
            q = norm(q + attend(q, q, q, need_weights=False)[0])
            outputs.append(output_norm(cross(q, x, x, need_weights=False)[0]))
        pooled = self.row_projection(torch.cat(outputs, dim=1).transpose(1, 2))  # [B, dim, rows]
        return F.normalize(pooled.flatten(1), dim=1)
