"""Mipmapped texture storage and trilinear sampling on a torch device."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


class TextureAtlas:
    """All textures of a scene with their mip pyramids, sampled with wrap-around addressing.

    Texture coordinates ``(u, v)`` are in texture periods (``[0, 1)`` covers one copy; ``u``
    to the right, ``v`` down the image rows); texel ``(i, j)`` of a level of size ``n`` is
    centred at ``((i + 0.5) / n, (j + 0.5) / n)``. Level ``l`` is the 2x2 box average of level
    ``l - 1``, so sampling at level ``log2(texels per pixel)`` area-filters the texture.
    """

    def __init__(self, textures: list[np.ndarray], device: torch.device):
        sizes = {texture.shape for texture in textures}
        if len(sizes) != 1:
            raise ValueError(f"all textures must share one shape [S, S, 4], got {sorted(sizes)}")
        stack = torch.from_numpy(np.stack(textures)).permute(0, 3, 1, 2).to(torch.float32)
        self.size = stack.shape[-1]
        self.max_level = int(np.log2(self.size))
        levels, offsets, total = [], [], 0
        level = stack
        for _ in range(self.max_level + 1):
            flat = (level.permute(0, 2, 3, 1) * 255.0).round().to(torch.uint8).reshape(-1, 4)
            levels.append(flat)
            offsets.append(total)
            total += flat.shape[0]
            level = F.avg_pool2d(level, 2) if level.shape[-1] > 1 else level
        self.texels = torch.cat(levels).to(device)
        self.offsets = torch.tensor(offsets, dtype=torch.int64, device=device)
        self.device = device

    def sample(self, texture: torch.Tensor, u: torch.Tensor, v: torch.Tensor, lod: torch.Tensor) -> torch.Tensor:
        """Trilinear samples ``[P, 4]`` (RGB + emission, in ``[0, 1]``) at mip level ``lod``."""
        lod = lod.clamp(0.0, float(self.max_level))
        lower = lod.floor()
        weight = (lod - lower)[:, None]
        lower = lower.to(torch.int64)
        upper = (lower + 1).clamp(max=self.max_level)
        fine = self._bilinear(texture, u, v, lower)
        coarse = self._bilinear(texture, u, v, upper)
        return fine + (coarse - fine) * weight

    def _bilinear(self, texture: torch.Tensor, u: torch.Tensor, v: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
        shift = self.max_level - level  # level size is 2^shift (a power of two)
        size = torch.bitwise_left_shift(torch.ones_like(level), shift)
        wrap = size - 1
        x = u * size - 0.5
        y = v * size - 0.5
        x0, y0 = x.floor(), y.floor()
        wx, wy = (x - x0)[:, None], (y - y0)[:, None]
        x0 = x0.to(torch.int64) & wrap
        y0 = y0.to(torch.int64) & wrap
        x1 = (x0 + 1) & wrap
        row0 = self.offsets[level] + torch.bitwise_left_shift(texture, 2 * shift) + torch.bitwise_left_shift(y0, shift)
        row1 = row0 - torch.bitwise_left_shift(y0, shift) + torch.bitwise_left_shift((y0 + 1) & wrap, shift)
        texels = self.texels[torch.stack([row0 + x0, row0 + x1, row1 + x0, row1 + x1])].to(torch.float32)
        top = texels[0] + (texels[1] - texels[0]) * wx
        bottom = texels[2] + (texels[3] - texels[2]) * wx
        return (top + (bottom - top) * wy) / 255.0
