"""DenseVLAD (Torii et al., CVPR 2015, "24/7 place recognition by view synthesis"; paper Sec. 3.8.2).

Dense upright RootSIFT at four scales on a regular grid, hard-assigned to a k-means
vocabulary, aggregated into an intra-normalised VLAD, then PCA-whitened and L2-normalised.
The vocabulary and the PCA are learned on the database images, so no weights are needed.

Following the authors' ``at_image2densevlad.m`` (``vl_phow`` defaults): SIFT bin sizes
4/6/8/10 px (region widths 16-40 px), a grid step of 2 px, each scale pre-smoothed by a
Gaussian of ``sqrt((bin / magnification)^2 - 0.25)`` px, cells weighted by a Gaussian
window of ``window_size`` bins, descriptors whose unnormalised norm is below
``contrast_threshold`` (grey levels in [0, 1]) rejected. Differences, all deliberate:
images larger than ``max_side`` px are shrunk to it (the original halves every image with
``vl_imdown``, "downsize to vga", which assumes 1280x960 input) and smaller ones are used as
they are (``upsample=True`` enlarges them to ``max_side``, which keeps the SIFT scales
comparable across image sizes at the cost of 1.8x the descriptors for 480 px images, and adds
no detail); rejected low-contrast descriptors are
left out of the VLAD (``vl_phow`` zeroes them, and a zero vector still adds ``-c_k`` to its
word's residual); vocabulary and PCA are learned on each database (the authors ship ones
learned on their own data), and the PCA is centred (their projection is applied to
uncentred VLADs).

Dense SIFT: the gradient-orientation histograms are kornia's (computed here without its
3 x 3 convolution, which dominated the run time); the spatial pooling is our own (a
depthwise triangle filter evaluated only on the sampled lattice), because kornia's
``DenseSIFTDescriptor`` pools each cell over ``bin_size`` px instead of VLFeat's bilinear
``2 * bin_size - 1``, has no cell window, and normalises without exposing the contrast
that ``vl_phow`` thresholds. Descriptors are built and assigned to their words a few grid
rows at a time, so the working set stays bounded whatever the image size.

Two implementations of the same maths: torch (`sift_lattice`, `SiftLattice.rootsift`, batches
of images; the reference, and the GPU path) and, on CPU, one image per thread through the numba
kernels of `locretrieval.models.densevlad_kernels` (`cpu_lattice`, `cpu_rootsift`) with a
single-threaded matrix product for the word assignment; they agree within float32 rounding.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import faiss
import kornia
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from locretrieval.device import resolve_device
from locretrieval.models import densevlad_kernels as kernels
from locretrieval.models.base import GlobalDescriptor
from locretrieval.models.densevlad_kernels import ANGLE_BINS, SIFT_CLIP
from locretrieval.models.densevlad_kernels import EPS as _EPS
from locretrieval.scene import ImageSet
from locretrieval.scene.images import read_image

log = logging.getLogger(__name__)

#: Bumped whenever a code change alters the descriptors (part of the cache key).
IMPLEMENTATION_VERSION = 3
SPATIAL_BINS = 4
SIFT_DIM = SPATIAL_BINS * SPATIAL_BINS * ANGLE_BINS
#: kornia's guard of the gradient magnitude and orientation.
_GRADIENT_EPS = 1e-10
#: Descriptors built and assigned at a time on a GPU (8 MB of them): fewer, larger chunks
#: were faster (fewer tensor operations), and the working set stays bounded.
CHUNK_POINTS = 16384
#: The same on CPU, one image per thread: 2048 descriptors (1 MB) and their word scores stay
#: in cache, where the single-threaded matrix product runs at ~70 GFLOP/s instead of ~50.
CPU_CHUNK_POINTS = 2048


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


def _window_weights(window_size: float, device: torch.device) -> torch.Tensor:
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
    magnification: float = 6.0,
    window_size: float = 1.5,
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
    return SiftLattice(pooled, geometry, _window_weights(window_size, images.device))


def dense_rootsift(
    images: torch.Tensor,
    bin_size: int,
    step: int,
    max_bin_size: int,
    magnification: float = 6.0,
    window_size: float = 1.5,
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
    image: torch.Tensor, bin_size: int, step: int, max_bin_size: int, magnification: float = 6.0
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


class VladAccumulator:
    """Sums of residuals ``x - c_k`` per visual word over descriptors added in chunks.

    Hard assignment to the nearest centroid (largest ``x . c - |c|^2 / 2``, the first on ties);
    ``centroids [K, D]``. With ``cpu_kernels`` (default: on CPU) the assignment is a matrix
    product and numpy's row argmax per image, the sums the numba kernel
    `densevlad_kernels.add_to_words`; otherwise torch, the whole batch at once.
    """

    def __init__(self, centroids: torch.Tensor, batch: int, cpu_kernels: bool | None = None) -> None:
        self.centroids = centroids
        self.batch = batch
        self.cpu_kernels = centroids.device.type == "cpu" if cpu_kernels is None else cpu_kernels
        self._centroids_t = centroids.T.contiguous()
        self._neg_half_norms = -0.5 * (centroids * centroids).sum(1)
        # One extra slot collects the invalid rows.
        self._sums = centroids.new_zeros(batch * len(centroids) + 1, centroids.shape[1])
        self._counts = torch.zeros(batch * len(centroids) + 1, dtype=torch.long, device=centroids.device)
        self._scores = centroids.new_empty(0, len(centroids))  # CPU: the word scores of a chunk, reused

    def add(self, descriptors: torch.Tensor, valid: torch.Tensor) -> None:
        """``descriptors [B, M, D]`` of the batch's images; rows where ``valid [B, M]`` is false are ignored."""
        num_words = len(self.centroids)
        if self.cpu_kernels:
            sums = self._sums[:-1].view(self.batch, num_words, -1).numpy()
            counts = self._counts[:-1].view(self.batch, num_words).numpy()
            if len(self._scores) < descriptors.shape[1]:
                self._scores = descriptors.new_empty(descriptors.shape[1], num_words)
            for image in range(self.batch):
                scores = torch.addmm(
                    self._neg_half_norms,
                    descriptors[image],
                    self._centroids_t,
                    out=self._scores[: descriptors.shape[1]],
                )
                kernels.add_to_words(
                    descriptors[image].numpy(),
                    scores.numpy().argmax(1),
                    valid[image].numpy(),
                    sums[image],
                    counts[image],
                )
            return
        scores = torch.addmm(self._neg_half_norms, descriptors.flatten(0, 1), self._centroids_t)
        slots = (
            scores.argmax(1).view(valid.shape)
            + num_words * torch.arange(self.batch, device=descriptors.device)[:, None]
        )
        slots = torch.where(valid, slots, self.batch * num_words).flatten()
        self._sums.index_add_(0, slots, descriptors.flatten(0, 1))
        self._counts += torch.bincount(slots, minlength=len(self._counts))

    def residuals(self) -> torch.Tensor:
        """``[B, K, D]`` (zeros for words without descriptors)."""
        counts = self._counts[:-1, None].to(self._sums.dtype)
        residuals = self._sums[:-1] - counts * self.centroids.repeat(self.batch, 1)
        return residuals.view(self.batch, len(self.centroids), -1)


def vlad_residuals(
    descriptors: torch.Tensor, valid: torch.Tensor, centroids: torch.Tensor, cpu_kernels: bool | None = None
) -> torch.Tensor:
    """`VladAccumulator` over one set of ``descriptors [B, M, D]``: residual sums ``[B, K, D]``."""
    accumulator = VladAccumulator(centroids, descriptors.shape[0], cpu_kernels)
    accumulator.add(descriptors, valid)
    return accumulator.residuals()


def normalize_vlad(residuals: torch.Tensor) -> torch.Tensor:
    """Intra-normalisation (L2 per word) then global L2: ``[B, K, D] -> [B, K * D]``."""
    return F.normalize(F.normalize(residuals, dim=-1, eps=_EPS).flatten(1), dim=-1, eps=_EPS)


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """torch's intra-op threads set to ``count`` (its BLAS included), restored afterwards."""
    previous = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


class DenseVLAD(GlobalDescriptor):
    """DenseVLAD with vocabulary and PCA-whitening learned on the database (see module doc).
    Every parameter comes from ``configs/model/densevlad.yaml`` (the one place of its defaults).

    Whitening divides principal component ``i`` by ``sqrt(lambda_i + r * lambda_1)``
    (``r = whitening_regularization``), which bounds the gain of near-zero eigenvalues.
    A database of ``N`` images supports at most ``N - 1`` components; fewer than
    ``pca_dim`` are used (and logged) when ``N <= pca_dim``.
    """

    learns_from_database = True

    def __init__(
        self,
        *,
        name: str,
        max_side: int,
        upsample: bool,
        step: int,
        bin_sizes: Sequence[int],
        magnification: float,
        window_size: float,
        contrast_threshold: float,
        num_words: int,
        vocabulary_images: int,
        vocabulary_samples: int,
        kmeans_iterations: int,
        pca_dim: int,
        whitening_regularization: float,
        seed: int,
        batch_size: int,
        device: str,
    ) -> None:
        super().__init__(name)
        self.max_side = int(max_side)
        self.upsample = bool(upsample)
        self.step = int(step)
        self.bin_sizes = tuple(int(size) for size in bin_sizes)
        self.magnification = float(magnification)
        self.window_size = float(window_size)
        self.contrast_threshold = float(contrast_threshold)
        self.num_words = int(num_words)
        self.vocabulary_images = int(vocabulary_images)
        self.vocabulary_samples = int(vocabulary_samples)
        self.kmeans_iterations = int(kmeans_iterations)
        self.pca_dim = int(pca_dim)
        self.whitening_regularization = float(whitening_regularization)
        self.seed = int(seed)
        self.batch_size = int(batch_size)
        self.device = resolve_device(device)
        positive = {
            "max_side": self.max_side,
            "step": self.step,
            "num_words": self.num_words,
            "vocabulary_images": self.vocabulary_images,
            "vocabulary_samples": self.vocabulary_samples,
            "kmeans_iterations": self.kmeans_iterations,
            "pca_dim": self.pca_dim,
            "batch_size": self.batch_size,
            "magnification": self.magnification,
            "window_size": self.window_size,
        }
        for key, value in positive.items():
            if value <= 0:
                raise ValueError(f"DenseVLAD: {key} must be positive, got {value}")
        if not self.bin_sizes or min(self.bin_sizes) < 1:
            raise ValueError(f"DenseVLAD: bin_sizes must be positive integers, got {list(self.bin_sizes)}")
        if self.contrast_threshold < 0 or self.whitening_regularization < 0:
            raise ValueError("DenseVLAD: contrast_threshold and whitening_regularization must be >= 0")
        self._centroids: torch.Tensor | None = None
        self._pca_mean: torch.Tensor | None = None
        self._pca_projection: torch.Tensor | None = None
        self._fitted_database: tuple[str, np.ndarray] | None = None

    def identity(self) -> dict[str, Any]:
        return {
            "model": "densevlad",
            "implementation": IMPLEMENTATION_VERSION,
            "max_side": self.max_side,
            "upsample": self.upsample,
            "step": self.step,
            "bin_sizes": list(self.bin_sizes),
            "magnification": self.magnification,
            "window_size": self.window_size,
            "contrast_threshold": self.contrast_threshold,
            "num_words": self.num_words,
            "vocabulary_images": self.vocabulary_images,
            "vocabulary_samples": self.vocabulary_samples,
            "kmeans_iterations": self.kmeans_iterations,
            "pca_dim": self.pca_dim,
            "whitening_regularization": self.whitening_regularization,
            "seed": self.seed,
        }

    # -- images -------------------------------------------------------------------------

    def _load(self, images: ImageSet, index: int) -> torch.Tensor:
        """Grey image ``[1, h, w]`` in [0, 1], its longer side shrunk to ``max_side`` (or enlarged: `upsample`)."""
        path = images.paths[index]
        grey = torch.tensor(read_image(path, grayscale=True), dtype=torch.float32, device=self.device) / 255.0
        height, width = grey.shape
        scale = self.max_side / max(height, width)
        if scale > 1 and not self.upsample:
            scale = 1.0
        size = (max(1, round(height * scale)), max(1, round(width * scale)))
        if min(size) < 3 * max(self.bin_sizes) + 1:
            raise ValueError(
                f"image {path} ({width}x{height} px) resized to {size[1]}x{size[0]} px is too small for "
                f"SIFT bins of {max(self.bin_sizes)} px; raise max_side, or set upsample=true for small images"
            )
        if size == (height, width):
            return grey[None]
        return F.interpolate(grey[None, None], size=size, mode="bilinear", antialias=True, align_corners=False)[0]

    def _batches(
        self, images: ImageSet, indices: Sequence[int], label: str
    ) -> Iterator[tuple[list[int], torch.Tensor]]:
        """Consecutive images of equal resized size, ``batch_size`` at a time: ``(indices, [b, 1, h, w])``."""
        pending: list[int] = []
        tensors: list[torch.Tensor] = []
        for index in tqdm(indices, desc=f"DenseVLAD {label}", unit="img", leave=False):
            tensor = self._load(images, index)
            if tensors and (tensor.shape != tensors[0].shape or len(tensors) == self.batch_size):
                yield pending, torch.stack(tensors)
                pending, tensors = [], []
            pending.append(index)
            tensors.append(tensor)
        if tensors:
            yield pending, torch.stack(tensors)

    def _for_each_batch(
        self, images: ImageSet, indices: Sequence[int], label: str, work: Callable[[list[int], torch.Tensor], None]
    ) -> None:
        """``work(indices, batch [b, 1, h, w])`` for every image: on CPU one image per task, a
        thread per torch thread, each with single-threaded torch; elsewhere `_batches` in turn."""
        if self.device.type != "cpu":
            for batch_indices, batch in self._batches(images, indices, label):
                work(batch_indices, batch)
            return

        def one(index: int) -> None:
            work([index], self._load(images, index)[None])

        workers = torch.get_num_threads()
        with torch_threads(1), ThreadPoolExecutor(workers) as pool:
            futures = [pool.submit(one, index) for index in indices]
            try:
                for future in tqdm(futures, desc=f"DenseVLAD {label}", unit="img", leave=False):
                    future.result()  # in order: the first failing image's error is raised
            except BaseException:
                for future in futures:
                    future.cancel()
                raise

    def _scale_descriptors(
        self, batch: torch.Tensor, max_points: int | None
    ) -> Iterator[tuple[int, torch.Tensor, torch.Tensor]]:
        """``(scale, descriptors [B, n, 128], contrast [B, n])`` of the batch's grid points, a few
        grid rows at a time (at most ``max_points`` descriptors, ``None``: a whole scale at
        once); on CPU (one image) by the numba kernels, which reuse one buffer: a chunk is
        valid until the next one is asked for."""
        max_bin_size = max(self.bin_sizes)
        if self.device.type != "cpu":
            for scale, bin_size in enumerate(self.bin_sizes):
                lattice = sift_lattice(batch, bin_size, self.step, max_bin_size, self.magnification, self.window_size)
                for rows in lattice.geometry.row_chunks(
                    max_points or lattice.geometry.rows * lattice.geometry.cols, len(batch)
                ):
                    descriptors, contrast = lattice.rootsift(lattice.cells[:, rows])
                    yield scale, descriptors.flatten(1, 2), contrast.flatten(1)
            return
        window = _window_weights(self.window_size, self.device).numpy()
        buffer = None
        for scale, bin_size in enumerate(self.bin_sizes):
            pooled, geometry = cpu_lattice(batch[0], bin_size, self.step, max_bin_size, self.magnification)
            if max_points is not None and buffer is None:
                buffer = np.empty((max(max_points, geometry.cols), SIFT_DIM), np.float32)
            for rows in geometry.row_chunks(max_points or geometry.rows * geometry.cols):
                descriptors, contrast = cpu_rootsift(pooled, geometry, rows, window, buffer)
                yield scale, torch.from_numpy(descriptors)[None], torch.from_numpy(contrast)[None]

    def _kept(self, contrast: torch.Tensor) -> torch.Tensor:
        """Descriptors whose contrast passes the threshold (zero contrast never does)."""
        return (contrast >= self.contrast_threshold) & (contrast > 0)

    # -- fitting --------------------------------------------------------------------------

    @torch.no_grad()
    def _learn_vocabulary(self, database: ImageSet) -> None:
        """k-means (faiss, spherical, seeded) on RootSIFTs sampled evenly from database images."""
        count = min(len(database), self.vocabulary_images)
        chosen = np.unique(np.linspace(0, len(database) - 1, count).round().astype(int))
        per_image_scale = math.ceil(self.vocabulary_samples / (len(chosen) * len(self.bin_sizes)))
        samples: dict[tuple[int, int], np.ndarray] = {}

        def sample(indices: list[int], batch: torch.Tensor) -> None:
            for scale, descriptors, contrast in self._scale_descriptors(batch, max_points=None):
                kept = self._kept(contrast)
                for row, image_index in enumerate(indices):
                    candidates = torch.nonzero(kept[row]).squeeze(1).cpu()
                    rng = np.random.default_rng([self.seed, image_index, scale])
                    take = np.sort(rng.choice(len(candidates), min(per_image_scale, len(candidates)), replace=False))
                    samples[image_index, scale] = descriptors[row, candidates[take].to(self.device)].cpu().numpy()

        self._for_each_batch(database, chosen.tolist(), "vocabulary", sample)
        points = np.ascontiguousarray(np.concatenate([samples[key] for key in sorted(samples)]), dtype=np.float32)
        if len(points) < self.num_words:
            raise ValueError(
                f"DenseVLAD: only {len(points)} descriptors above contrast {self.contrast_threshold} in the "
                f"database, fewer than the {self.num_words} visual words"
            )
        kmeans = faiss.Kmeans(
            SIFT_DIM,
            self.num_words,
            niter=self.kmeans_iterations,
            seed=self.seed,
            spherical=True,
            max_points_per_centroid=math.ceil(len(points) / self.num_words),
        )
        kmeans.train(points)
        self._centroids = torch.from_numpy(kmeans.centroids.copy()).to(self.device)
        log.info(
            "DenseVLAD: %d-word vocabulary from %d descriptors of %d images", self.num_words, len(points), len(chosen)
        )

    def _learn_whitening(self, vlads: np.ndarray) -> None:
        """Centred PCA (faiss) to ``min(pca_dim, N - 1)`` dims with regularised whitening."""
        if len(vlads) < 2:
            raise ValueError("DenseVLAD needs at least 2 database images to learn its PCA whitening")
        dim = min(self.pca_dim, len(vlads) - 1)
        if dim < self.pca_dim:
            log.info(
                "DenseVLAD: %d database images support %d PCA dimensions (configured %d)", len(vlads), dim, self.pca_dim
            )
        pca = faiss.PCAMatrix(vlads.shape[1], dim, 0.0, False)
        pca.train(np.ascontiguousarray(vlads, dtype=np.float32))
        eigenvalues = faiss.vector_to_array(pca.eigenvalues)[:dim].astype(np.float64)
        if eigenvalues[0] <= 0:
            raise ValueError("DenseVLAD: all database VLADs are identical; PCA whitening is undefined")
        components = faiss.vector_to_array(pca.PCAMat).reshape(-1, vlads.shape[1])[:dim]
        scale = 1.0 / np.sqrt(np.maximum(eigenvalues, 0.0) + self.whitening_regularization * eigenvalues[0])
        self._pca_mean = torch.from_numpy(faiss.vector_to_array(pca.mean).copy()).to(self.device)
        self._pca_projection = torch.from_numpy((components.T * scale).astype(np.float32)).to(self.device)

    def fit(self, database: ImageSet) -> None:
        """Learn the vocabulary, then the PCA-whitening on the database VLADs."""
        self._fitted_database = None
        self._learn_vocabulary(database)
        vlads = self._vlads(database)
        self._learn_whitening(vlads)
        self._fitted_database = (database.fingerprint(include_poses=False), self._whiten(vlads))
        log.info("DenseVLAD fitted on %d database images: %d dimensions", len(database), self._pca_projection.shape[1])

    def _require_fitted(self) -> None:
        if self._centroids is None or self._pca_projection is None:
            raise RuntimeError(
                "DenseVLAD is not fitted: call fit(database) first (describe_scene does when its "
                "descriptor cache misses; a cache hit leaves the model unfitted)"
            )

    # -- description ----------------------------------------------------------------------

    @torch.no_grad()
    def _vlads(self, images: ImageSet) -> np.ndarray:
        """Intra-normalised, L2-normalised VLADs ``float32 [N, num_words * 128]`` before PCA."""
        if self._centroids is None:
            raise RuntimeError("DenseVLAD has no vocabulary: call fit(database) first (describe_scene does)")
        vlads = np.empty((len(images), self._centroids.numel()), dtype=np.float32)

        def describe(indices: list[int], batch: torch.Tensor) -> None:
            accumulator = VladAccumulator(self._centroids, len(indices))
            chunk = CPU_CHUNK_POINTS if self.device.type == "cpu" else CHUNK_POINTS
            for _, descriptors, contrast in self._scale_descriptors(batch, chunk):
                accumulator.add(descriptors, self._kept(contrast))
            vlads[indices] = normalize_vlad(accumulator.residuals()).cpu().numpy()

        self._for_each_batch(images, range(len(images)), "describe", describe)
        return vlads

    @torch.no_grad()
    def _whiten(self, vlads: np.ndarray) -> np.ndarray:
        """PCA-whitened, L2-normalised descriptors ``float32 [N, dims]``."""
        self._require_fitted()
        out = np.empty((len(vlads), self._pca_projection.shape[1]), dtype=np.float32)
        for start in range(0, len(vlads), 256):
            chunk = torch.from_numpy(vlads[start : start + 256]).to(self.device)
            whitened = (chunk - self._pca_mean) @ self._pca_projection
            out[start : start + 256] = F.normalize(whitened, dim=-1).cpu().numpy()
        return out

    def describe(self, images: ImageSet) -> np.ndarray:
        """Descriptors of ``images``; the database seen by `fit` is not described twice."""
        self._require_fitted()
        if self._fitted_database is not None and self._fitted_database[0] == images.fingerprint(include_poses=False):
            return self._fitted_database[1].copy()
        return self._whiten(self._vlads(images))
