"""Dense upright RootSIFT on a regular grid, as VLFeat's ``vl_phow`` computes it (DenseVLAD's
local descriptors; `locretrieval.models.published.densevlad`).

The gradient-orientation histograms are kornia's (computed here without its 3 x 3 convolution,
which dominated the run time); the spatial pooling is our own (a depthwise triangle filter
evaluated only on the sampled lattice), because kornia's ``DenseSIFTDescriptor`` pools each cell
over ``bin_size`` px instead of VLFeat's bilinear ``2 * bin_size - 1``, has no cell window, and
normalises without exposing the contrast that ``vl_phow`` thresholds. Descriptors are built a few
grid rows at a time (`LatticeGeometry.row_chunks`), so the working set stays bounded whatever the
image size.

Two implementations of the same maths: torch (`sift_lattice`, `SiftLattice.rootsift`, batches of
images; the reference, and the GPU path) and, on CPU, one image per thread through the numba
kernels of `locretrieval.models.published.densevlad_kernels` (`cpu_lattice`, `cpu_rootsift`); they agree
within float32 rounding.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import kornia
import numpy as np
import torch
import torch.nn.functional as F

from locretrieval.models.published import densevlad_kernels as kernels
from locretrieval.models.published.densevlad_kernels import ANGLE_BINS, SIFT_CLIP
from locretrieval.models.published.densevlad_kernels import EPS as _EPS

SPATIAL_BINS = 4
SIFT_DIM = SPATIAL_BINS * SPATIAL_BINS * ANGLE_BINS
#: kornia's guard of the gradient magnitude and orientation.
_GRADIENT_EPS = 1e-10


def grid_layout(size: int, max_bin_size: int, step: int) -> tuple[int, int]:
    """``(first, count)``: descriptor centres ``first + i * step`` along an axis of ``size`` px.

    The grid is shared by every bin size up to ``max_bin_size``: the outermost cell centres
    of the widest descriptor lie inside the image (pixel-centre coordinates, first pixel 0).
    """
    first = (3 * max_bin_size) // 2
    last = size - 1 - (3 * max_bin_size + 1) // 2
    return first, max(0, (last - first) // step + 1)


@dataclass(frozen=True)
class LatticeGeometry:
    """Where the cells of one SIFT scale fall: ``rows x cols`` grid points; lattice entry
    ``(j, i)`` is the pixel ``(origin_y + j * stride, origin_x + i * stride)``, the first grid
    point's first cell centre is entry ``(0, 0)``, cells are ``cell_step`` entries apart and grid
    points ``grid_step``; ``lattice_rows x lattice_cols`` entries hold every cell."""

    rows: int
    cols: int
    origin_y: int
    origin_x: int
    stride: int
    cell_step: int
    grid_step: int

    @property
    def lattice_rows(self) -> int:
        return (self.rows - 1) * self.grid_step + (SPATIAL_BINS - 1) * self.cell_step + 1

    @property
    def lattice_cols(self) -> int:
        return (self.cols - 1) * self.grid_step + (SPATIAL_BINS - 1) * self.cell_step + 1

    def row_chunks(self, max_points: int, images: int = 1) -> Iterator[slice]:
        """Slices of grid rows holding at most ``max_points`` descriptors of ``images`` images (one row at least)."""
        step = max(1, max_points // (images * self.cols))
        for start in range(0, self.rows, step):
            yield slice(start, min(start + step, self.rows))


def lattice_geometry(height: int, width: int, bin_size: int, step: int, max_bin_size: int) -> LatticeGeometry:
    """The `LatticeGeometry` of SIFT bins of ``bin_size`` px on the grid of `grid_layout`."""
    first_y, rows = grid_layout(height, max_bin_size, step)
    first_x, cols = grid_layout(width, max_bin_size, step)
    if rows == 0 or cols == 0:
        raise ValueError(f"image of {width}x{height} px is too small for SIFT bins of {max_bin_size} px")
    stride = math.gcd(step, bin_size)
    first_cell = (3 * bin_size) // 2
    return LatticeGeometry(
        rows, cols, first_y - first_cell, first_x - first_cell, stride, bin_size // stride, step // stride
    )


def _triangle_kernel(bin_size: int, device: torch.device) -> torch.Tensor:
    """Bilinear spatial-binning weights ``1 - |d| / bin_size`` for ``|d| < bin_size``."""
    offsets = torch.arange(1 - bin_size, bin_size, device=device, dtype=torch.float32)
    return 1.0 - offsets.abs() / bin_size


def window_weights(window_size: float, device: torch.device) -> torch.Tensor:
    """Gaussian weight ``[16]`` of each spatial cell (row-major), sigma ``window_size`` bins."""
    offsets = torch.arange(SPATIAL_BINS, device=device, dtype=torch.float32) - (SPATIAL_BINS - 1) / 2
    weights = torch.exp(-0.5 * (offsets / window_size) ** 2)
    return torch.outer(weights, weights).flatten()


def smoothed(images: torch.Tensor, bin_size: int, magnification: float) -> torch.Tensor:
    """``images [B, 1, H, W]`` pre-smoothed for SIFT bins of ``bin_size`` px (``vl_phow``): a
    Gaussian of sigma ``sqrt((bin_size / magnification)^2 - 0.25)`` px, none when that is not real."""
    sigma_squared = (bin_size / magnification) ** 2 - 0.25
    if sigma_squared <= 0:
        return images
    sigma = math.sqrt(sigma_squared)
    kernel_size = 2 * math.ceil(3 * sigma) + 1
    return kornia.filters.gaussian_blur2d(images, (kernel_size, kernel_size), (sigma, sigma))


def gradient_orientations(images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(magnitude, position) [B, H, W]`` of the gradients of ``[B, 1, H, W]``, as kornia's
    ``DenseSIFTDescriptor`` computes them: central differences ``(I[x + 1] - I[x - 1]) / 2`` with
    replicated borders, magnitude ``sqrt(gx^2 + gy^2 + 1e-10)`` (zero where the gradient is),
    ``position`` the orientation ``atan2(gy, gx)`` in bins (8 per turn, bin 0 centred on angle 0,
    values in [4, 12])."""
    padded = F.pad(images, (1, 1, 1, 1), mode="replicate")[:, 0]
    gx = 0.5 * (padded[:, 1:-1, 2:] - padded[:, 1:-1, :-2])
    gy = 0.5 * (padded[:, 2:, 1:-1] - padded[:, :-2, 1:-1])
    squared = gx * gx + gy * gy
    nonzero = squared > 0
    magnitude = torch.where(nonzero, torch.sqrt(squared + _GRADIENT_EPS), 0.0)
    angle = torch.where(nonzero, torch.atan2(gy, gx + _GRADIENT_EPS) + 2.0 * math.pi, 2.0 * math.pi)
    return magnitude, angle * (ANGLE_BINS / (2.0 * math.pi))


def gradient_histograms(images: torch.Tensor) -> torch.Tensor:
    """Per-pixel orientation histograms ``[B, 8, H, W]`` (channels-last memory) of ``[B, 1, H, W]``:
    each gradient (`gradient_orientations`) votes linearly into its two nearest of 8 bins
    (kornia's ``DenseSIFTDescriptor.get_gradient_histograms`` without its 3 x 3 convolution)."""
    magnitude, position = gradient_orientations(images)
    lower = torch.floor(position)
    upper_weight = position - lower
    lower_bin = lower.long().remainder_(ANGLE_BINS)
    histograms = images.new_zeros(*magnitude.shape, ANGLE_BINS)  # [B, H, W, 8]
    histograms.scatter_add_(-1, lower_bin[..., None], ((1.0 - upper_weight) * magnitude)[..., None])
    histograms.scatter_add_(-1, ((lower_bin + 1) % ANGLE_BINS)[..., None], (upper_weight * magnitude)[..., None])
    return histograms.permute(0, 3, 1, 2)


class SiftLattice:
    """One SIFT scale of a batch (torch): pooled gradient histograms where descriptor cells fall.

    ``pooled [B, Y, X, 8]`` holds the bilinearly pooled histograms on the lattice of
    ``geometry``; ``cells`` views them as ``[B, rows, cols, 4, 4, 8]`` (grid point, cell row,
    cell column, angle) without copying, so descriptors are built a few grid rows at a time.
    """

    def __init__(self, pooled: torch.Tensor, geometry: LatticeGeometry, window: torch.Tensor) -> None:
        self.pooled = pooled
        self.geometry = geometry
        self.window = window.view(SPATIAL_BINS, SPATIAL_BINS, 1)
        self.cells = self._cell_view(pooled)

    def _cell_view(self, lattice: torch.Tensor) -> torch.Tensor:
        """``[B, Y, X, ...] -> [B, rows, cols, 4, 4, ...]``: each grid point's 4 x 4 cells (a view)."""
        geometry = self.geometry
        span = (SPATIAL_BINS - 1) * geometry.cell_step + 1
        windows = lattice.unfold(1, span, geometry.grid_step)[:, : geometry.rows]
        windows = windows.unfold(2, span, geometry.grid_step)[:, :, : geometry.cols]  # [B, rows, cols, ..., span, span]
        windows = windows[..., :: geometry.cell_step, :: geometry.cell_step]
        return windows.movedim((-2, -1), (3, 4))

    def rootsift(self, cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """RootSIFT ``[..., 128]`` of a selection ``[..., 4, 4, 8]`` of `cells`, and its contrast ``[...]``.

        SIFT's L2 / clip 0.2 / L2 followed by RootSIFT's L1 and square root (the second L2
        cancels in the L1 step); zero contrast gives a zero descriptor. The contrast is the
        L2 norm of the window-weighted histogram before normalisation.
        """
        descriptors = torch.mul(cells, self.window, out=cells.new_empty(cells.shape)).flatten(-3)
        contrast = torch.linalg.vector_norm(descriptors, dim=-1, keepdim=True)
        descriptors = descriptors.div_(contrast.clamp_min(_EPS)).clamp_max_(SIFT_CLIP)
        return descriptors.div_(descriptors.sum(-1, keepdim=True).clamp_min_(_EPS)).sqrt_(), contrast[..., 0]


def sift_lattice(
    images: torch.Tensor,
    bin_size: int,
    step: int,
    max_bin_size: int,
    magnification: float,
    window_size: float,
) -> SiftLattice:
    """Upright SIFT cells on the grid of `grid_layout` at one scale (torch, any device).

    ``images``: grey levels in [0, 1], ``float32 [B, 1, H, W]``. Gradient orientation
    histograms as kornia computes them (central differences, 8 bins, linear angular
    interpolation); cells are ``bin_size`` px apart and pool bilinearly (VLFeat
    ``vl_dsift`` geometry: a triangle of ``2 * bin_size - 1`` px, pixels outside the image
    count as zero), weighted by a Gaussian window of ``window_size`` bins.
    """
    _, _, height, width = images.shape
    geometry = lattice_geometry(height, width, bin_size, step, max_bin_size)
    histograms = gradient_histograms(smoothed(images, bin_size, magnification))
    # Every sampled cell centre lies on the lattice, so the bilinear pooling (a depthwise
    # separable triangle filter) is only evaluated there: zero-padded by the filter's reach,
    # the window of lattice entry j starts at padded pixel origin + j * stride.
    reach = bin_size - 1
    padded = F.pad(histograms, (reach, reach, reach, reach))[:, :, geometry.origin_y :, geometry.origin_x :]
    triangle = _triangle_kernel(bin_size, images.device)
    pooled = F.conv2d(
        padded, triangle.view(1, 1, -1, 1).expand(ANGLE_BINS, 1, -1, 1), stride=(geometry.stride, 1), groups=ANGLE_BINS
    )
    pooled = F.conv2d(
        pooled, triangle.view(1, 1, 1, -1).expand(ANGLE_BINS, 1, 1, -1), stride=(1, geometry.stride), groups=ANGLE_BINS
    )
    pooled = pooled[:, :, : geometry.lattice_rows, : geometry.lattice_cols].permute(0, 2, 3, 1)  # [B, Y, X, angle]
    return SiftLattice(pooled, geometry, window_weights(window_size, images.device))


def dense_rootsift(
    images: torch.Tensor,
    bin_size: int,
    step: int,
    max_bin_size: int,
    magnification: float,
    window_size: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Every RootSIFT of `sift_lattice` at once: ``(descriptors [B, G, 128], contrast [B, G])``.

    ``G`` grid points in row-major order, entries ordered (cell row, cell column, angle);
    descriptors are non-negative with unit L2 norm; ``contrast`` is the L2 norm of the
    window-weighted histogram before normalisation.
    """
    lattice = sift_lattice(images, bin_size, step, max_bin_size, magnification, window_size)
    descriptors, contrast = lattice.rootsift(lattice.cells)
    return descriptors.flatten(1, 2), contrast.flatten(1)


def cpu_lattice(
    image: torch.Tensor, bin_size: int, step: int, max_bin_size: int, magnification: float
) -> tuple[np.ndarray, LatticeGeometry]:
    """`sift_lattice`'s pooled histograms of one CPU image ``[1, H, W]`` by the numba kernels:
    ``(pooled [Y, X * 8], geometry)``."""
    _, height, width = image.shape
    geometry = lattice_geometry(height, width, bin_size, step, max_bin_size)
    magnitude, position = gradient_orientations(smoothed(image[None], bin_size, magnification))
    histograms = kernels.orientation_histograms(magnitude[0].numpy(), position[0].numpy())
    triangle = _triangle_kernel(bin_size, image.device).numpy()
    pooled = kernels.pooled_lattice(
        histograms,
        triangle,
        geometry.origin_y,
        geometry.origin_x,
        geometry.stride,
        geometry.lattice_rows,
        geometry.lattice_cols,
    )
    return pooled, geometry


def cpu_rootsift(
    pooled: np.ndarray, geometry: LatticeGeometry, rows: slice, window: np.ndarray, out: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """RootSIFT of the grid ``rows`` of a `cpu_lattice` (all columns, row-major) and their
    contrast: ``(descriptors [M, 128], contrast [M])``, as `SiftLattice.rootsift` computes them;
    ``out``: a buffer of at least ``M`` rows to write them into."""
    count = (rows.stop - rows.start) * geometry.cols
    descriptors = np.empty((count, SIFT_DIM), np.float32) if out is None else out[:count]
    contrast = np.empty(count, np.float32)
    kernels.rootsift_rows(
        pooled,
        window,
        rows.start,
        rows.stop,
        geometry.cols,
        geometry.cell_step,
        geometry.grid_step,
        descriptors,
        contrast,
    )
    return descriptors, contrast
