"""DenseVLAD (Torii et al., CVPR 2015, "24/7 place recognition by view synthesis"; paper Sec. 3.8.2).

Dense upright RootSIFT at four scales on a regular grid, hard-assigned to a k-means
vocabulary, aggregated into an intra-normalised VLAD, then PCA-whitened and L2-normalised.
The vocabulary and the PCA are learned on the database images, so no weights are needed.

Following the authors' ``at_image2densevlad.m`` (``vl_phow`` defaults): SIFT bin sizes
4/6/8/10 px (region widths 16-40 px), a grid step of 2 px, each scale pre-smoothed by a
Gaussian of ``sqrt((bin / magnification)^2 - 0.25)`` px, cells weighted by a Gaussian
window of ``window_size`` bins, descriptors whose unnormalised norm is below
``contrast_threshold`` (grey levels in [0, 1]) rejected. Differences, all deliberate:
images are resized so their longer side is ``max_side`` px (the original halves every
image with ``vl_imdown``, "downsize to vga", which assumes 1280x960 input; a fixed size
keeps the SIFT scales comparable across datasets); rejected low-contrast descriptors are
left out of the VLAD (``vl_phow`` zeroes them, and a zero vector still adds ``-c_k`` to its
word's residual); vocabulary and PCA are learned on each database (the authors ship ones
learned on their own data), and the PCA is centred (their projection is applied to
uncentred VLADs).

Dense SIFT: kornia computes the gradient-orientation histograms; the spatial pooling is our
own (a depthwise triangle filter evaluated only on the sampled lattice), because kornia's
``DenseSIFTDescriptor`` pools each cell over ``bin_size`` px instead of VLFeat's bilinear
``2 * bin_size - 1``, has no cell window, and normalises without exposing the contrast
that ``vl_phow`` thresholds.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Sequence
from typing import Any

import faiss
import kornia
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from locretrieval.device import resolve_device
from locretrieval.models.base import GlobalDescriptor
from locretrieval.scene import ImageSet
from locretrieval.scene.images import read_image

log = logging.getLogger(__name__)

#: Bumped whenever a code change alters the descriptors (part of the cache key).
IMPLEMENTATION_VERSION = 1
SPATIAL_BINS = 4
ANGLE_BINS = 8
SIFT_DIM = SPATIAL_BINS * SPATIAL_BINS * ANGLE_BINS
#: SIFT's clipping of single dominant bins, applied between two L2 normalisations.
SIFT_CLIP = 0.2
_EPS = 1e-12


def grid_layout(size: int, max_bin_size: int, step: int) -> tuple[int, int]:
    """``(first, count)``: descriptor centres ``first + i * step`` along an axis of ``size`` px.

    The grid is shared by every bin size up to ``max_bin_size``: the outermost cell centres
    of the widest descriptor lie inside the image (pixel-centre coordinates, first pixel 0).
    """
    first = (3 * max_bin_size) // 2
    last = size - 1 - (3 * max_bin_size + 1) // 2
    return first, max(0, (last - first) // step + 1)


def _triangle_kernel(bin_size: int, device: torch.device) -> torch.Tensor:
    """Bilinear spatial-binning weights ``1 - |d| / bin_size`` for ``|d| < bin_size``."""
    offsets = torch.arange(1 - bin_size, bin_size, device=device, dtype=torch.float32)
    return 1.0 - offsets.abs() / bin_size


def _window_weights(window_size: float, device: torch.device) -> torch.Tensor:
    """Gaussian weight ``[16]`` of each spatial cell (row-major), sigma ``window_size`` bins."""
    offsets = torch.arange(SPATIAL_BINS, device=device, dtype=torch.float32) - (SPATIAL_BINS - 1) / 2
    weights = torch.exp(-0.5 * (offsets / window_size) ** 2)
    return torch.outer(weights, weights).flatten()


def dense_rootsift(
    images: torch.Tensor,
    bin_size: int,
    step: int,
    max_bin_size: int,
    magnification: float = 6.0,
    window_size: float = 1.5,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Upright RootSIFT on the grid of `grid_layout` at one scale.

    ``images``: grey levels in [0, 1], ``float32 [B, 1, H, W]``. Gradient orientation
    histograms come from kornia (central differences, 8 bins, linear angular
    interpolation); cells are ``bin_size`` px apart and pool bilinearly (VLFeat
    ``vl_dsift`` geometry). Returns ``(descriptors [B, G, 128], contrast [B, G])`` with
    ``G`` grid points in row-major order, entries ordered (cell row, cell column, angle).
    Descriptors are SIFT-normalised (L2, clip 0.2, L2) then RootSIFT (L1, sqrt), hence
    non-negative with unit L2 norm; ``contrast`` is the L2 norm of the window-weighted
    histogram before normalisation (zero contrast gives a zero descriptor).
    """
    batch, _, height, width = images.shape
    first_y, rows = grid_layout(height, max_bin_size, step)
    first_x, cols = grid_layout(width, max_bin_size, step)
    if rows == 0 or cols == 0:
        raise ValueError(f"image of {width}x{height} px is too small for SIFT bins of {max_bin_size} px")
    sigma_squared = (bin_size / magnification) ** 2 - 0.25
    if sigma_squared > 0:
        sigma = math.sqrt(sigma_squared)
        kernel_size = 2 * math.ceil(3 * sigma) + 1
        images = kornia.filters.gaussian_blur2d(images, (kernel_size, kernel_size), (sigma, sigma))
    histograms = kornia.feature.DenseSIFTDescriptor(num_ang_bins=ANGLE_BINS).get_gradient_histograms(images)

    # Every sampled cell centre lies on the lattice origin + stride * j, so the bilinear pooling
    # (a depthwise separable triangle filter) is only evaluated there.
    stride = math.gcd(step, bin_size)
    origin_y = first_y - (3 * bin_size) // 2
    origin_x = first_x - (3 * bin_size) // 2
    histograms = histograms[:, :, origin_y % stride :, origin_x % stride :]
    triangle = _triangle_kernel(bin_size, images.device)
    pooled = F.conv2d(
        histograms,
        triangle.view(1, 1, -1, 1).expand(ANGLE_BINS, 1, -1, 1),
        padding=(bin_size - 1, 0),
        stride=(stride, 1),
        groups=ANGLE_BINS,
    )
    pooled = F.conv2d(
        pooled,
        triangle.view(1, 1, 1, -1).expand(ANGLE_BINS, 1, 1, -1),
        padding=(0, bin_size - 1),
        stride=(1, stride),
        groups=ANGLE_BINS,
    ).permute(0, 2, 3, 1)  # [B, y, x, angle] on the lattice

    cell_step, grid_step = bin_size // stride, step // stride
    top, left = origin_y // stride, origin_x // stride
    cells = [
        pooled[
            :,
            top + cell_y * cell_step : top + cell_y * cell_step + grid_step * (rows - 1) + 1 : grid_step,
            left + cell_x * cell_step : left + cell_x * cell_step + grid_step * (cols - 1) + 1 : grid_step,
        ]
        for cell_y in range(SPATIAL_BINS)
        for cell_x in range(SPATIAL_BINS)
    ]
    histogram = torch.stack(cells, -2).mul_(_window_weights(window_size, images.device)[:, None])
    histogram = histogram.reshape(batch, rows * cols, SIFT_DIM)
    contrast = histogram.norm(dim=-1)
    # SIFT's L2 / clip / L2 followed by RootSIFT's L1: the second L2 cancels in the L1 step.
    descriptors = histogram.div_(contrast.clamp_min(_EPS)[..., None]).clamp_max_(SIFT_CLIP)
    descriptors = descriptors.div_(descriptors.sum(-1, keepdim=True).clamp_min_(_EPS)).sqrt_()
    return descriptors, contrast


def vlad_residuals(descriptors: torch.Tensor, valid: torch.Tensor, centroids: torch.Tensor) -> torch.Tensor:
    """Sum of residuals ``x - c_k`` per visual word, hard assignment to the nearest centroid.

    ``descriptors [B, M, D]``, ``valid`` boolean ``[B, M]`` (invalid rows are ignored),
    ``centroids [K, D]``; returns ``[B, K, D]`` (zeros for words without descriptors).
    """
    batch, _, dim = descriptors.shape
    num_words = centroids.shape[0]
    scores = torch.matmul(descriptors, centroids.T).sub_(0.5 * (centroids * centroids).sum(1))
    slots = scores.argmax(-1) + num_words * torch.arange(batch, device=descriptors.device)[:, None]
    slots = torch.where(valid, slots, batch * num_words).flatten()  # one extra slot collects the invalid rows
    sums = descriptors.new_zeros(batch * num_words + 1, dim).index_add_(0, slots, descriptors.flatten(0, 1))
    counts = torch.bincount(slots, minlength=batch * num_words + 1).to(descriptors.dtype)
    return (sums[:-1] - counts[:-1, None] * centroids.repeat(batch, 1)).view(batch, num_words, dim)


def normalize_vlad(residuals: torch.Tensor) -> torch.Tensor:
    """Intra-normalisation (L2 per word) then global L2: ``[B, K, D] -> [B, K * D]``."""
    return F.normalize(F.normalize(residuals, dim=-1, eps=_EPS).flatten(1), dim=-1, eps=_EPS)


class DenseVLAD(GlobalDescriptor):
    """DenseVLAD with vocabulary and PCA-whitening learned on the database (see module doc).

    Whitening divides principal component ``i`` by ``sqrt(lambda_i + r * lambda_1)``
    (``r = whitening_regularization``), which bounds the gain of near-zero eigenvalues.
    A database of ``N`` images supports at most ``N - 1`` components; fewer than
    ``pca_dim`` are used (and logged) when ``N <= pca_dim``.
    """

    learns_from_database = True

    def __init__(
        self,
        name: str = "densevlad",
        max_side: int = 640,
        step: int = 2,
        bin_sizes: Sequence[int] = (4, 6, 8, 10),
        magnification: float = 6.0,
        window_size: float = 1.5,
        contrast_threshold: float = 0.005,
        num_words: int = 128,
        vocabulary_images: int = 500,
        vocabulary_samples: int = 100_000,
        kmeans_iterations: int = 25,
        pca_dim: int = 4096,
        whitening_regularization: float = 1e-3,
        seed: int = 0,
        batch_size: int = 4,
        device: str = "auto",
    ) -> None:
        super().__init__(name)
        self.max_side = int(max_side)
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
        """Grey image ``[1, h, w]`` in [0, 1] with its longer side resized to ``max_side``."""
        path = images.paths[index]
        grey = torch.tensor(read_image(path, grayscale=True), dtype=torch.float32, device=self.device) / 255.0
        height, width = grey.shape
        scale = self.max_side / max(height, width)
        size = (max(1, round(height * scale)), max(1, round(width * scale)))
        if min(size) < 3 * max(self.bin_sizes) + 1:
            raise ValueError(
                f"image {path} ({width}x{height} px) resized to {size[1]}x{size[0]} px is too small for "
                f"SIFT bins of {max(self.bin_sizes)} px; raise max_side"
            )
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

    def _rootsift_scales(self, batch: torch.Tensor) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """``(descriptors [B, G, 128], kept [B, G])`` per bin size; ``kept`` passes the contrast threshold."""
        for bin_size in self.bin_sizes:
            descriptors, contrast = dense_rootsift(
                batch, bin_size, self.step, max(self.bin_sizes), self.magnification, self.window_size
            )
            yield descriptors, (contrast >= self.contrast_threshold) & (contrast > 0)

    # -- fitting --------------------------------------------------------------------------

    @torch.no_grad()
    def _learn_vocabulary(self, database: ImageSet) -> None:
        """k-means (faiss, spherical, seeded) on RootSIFTs sampled evenly from database images."""
        count = min(len(database), self.vocabulary_images)
        chosen = np.unique(np.linspace(0, len(database) - 1, count).round().astype(int))
        per_image_scale = math.ceil(self.vocabulary_samples / (len(chosen) * len(self.bin_sizes)))
        samples = []
        for indices, batch in self._batches(database, chosen.tolist(), "vocabulary"):
            for scale, (descriptors, kept) in enumerate(self._rootsift_scales(batch)):
                for row, image_index in enumerate(indices):
                    candidates = torch.nonzero(kept[row]).squeeze(1)
                    rng = np.random.default_rng([self.seed, image_index, scale])
                    take = np.sort(rng.choice(len(candidates), min(per_image_scale, len(candidates)), replace=False))
                    samples.append(descriptors[row, candidates[torch.from_numpy(take).to(self.device)]].cpu().numpy())
        points = np.ascontiguousarray(np.concatenate(samples), dtype=np.float32)
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
        for indices, batch in self._batches(images, range(len(images)), "describe"):
            residuals = sum(
                vlad_residuals(descriptors, kept, self._centroids)
                for descriptors, kept in self._rootsift_scales(batch)
            )
            vlads[indices] = normalize_vlad(residuals).cpu().numpy()
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
