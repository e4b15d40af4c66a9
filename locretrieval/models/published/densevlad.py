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

The parts: dense RootSIFT in `locretrieval.models.published.dense_sift` (torch batches on a GPU, numba
kernels one image per thread on CPU), the vocabulary, VLAD and whitening in
`locretrieval.models.published.vlad`; this module loads and batches the images and learns and applies the
model on a database.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from locretrieval.device import resolve_device
from locretrieval.models.base import GlobalDescriptor
from locretrieval.models.published.dense_sift import SIFT_DIM, cpu_lattice, cpu_rootsift, sift_lattice, window_weights
from locretrieval.models.published.densevlad_kernels import EPS
from locretrieval.models.published.vlad import VladAccumulator, kmeans_vocabulary, normalize_vlad, pca_whitening
from locretrieval.scene import ImageSet
from locretrieval.scene.images import read_image
from locretrieval.threads import map_single_threaded, torch_threads

log = logging.getLogger(__name__)

#: Bumped whenever a code change alters the descriptors (part of the cache key).
IMPLEMENTATION_VERSION = 4
#: Descriptors built and assigned at a time on a GPU (8 MB of them): fewer, larger chunks
#: were faster (fewer tensor operations), and the working set stays bounded.
CHUNK_POINTS = 16384
#: The same on CPU, one image per thread: 2048 descriptors (1 MB) and their word scores stay
#: in cache, where the single-threaded matrix product runs at ~70 GFLOP/s instead of ~50.
CPU_CHUNK_POINTS = 2048
#: VLADs whitened at a time (a fixed chunk: its product's arithmetic does not follow the thread count).
WHITENING_ROWS = 256


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
        window = window_weights(self.window_size, self.device).numpy()
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
        """Spherical k-means (`kmeans_vocabulary`, seeded) on RootSIFTs sampled evenly from database images."""
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
        centroids = kmeans_vocabulary(points, self.num_words, self.kmeans_iterations, self.seed)
        self._centroids = torch.from_numpy(centroids).to(self.device)
        log.info(
            "DenseVLAD: %d-word vocabulary from %d descriptors of %d images", self.num_words, len(points), len(chosen)
        )

    def _learn_whitening(self, vlads: np.ndarray) -> None:
        """Centred PCA to ``min(pca_dim, N - 1)`` dims with regularised whitening (`pca_whitening`)."""
        if len(vlads) < 2:
            raise ValueError("DenseVLAD needs at least 2 database images to learn its PCA whitening")
        dim = min(self.pca_dim, len(vlads) - 1)
        if dim < self.pca_dim:
            log.info(
                "DenseVLAD: %d database images support %d PCA dimensions (configured %d)", len(vlads), dim, self.pca_dim
            )
        mean, projection = pca_whitening(vlads, dim, self.whitening_regularization)
        self._pca_mean = torch.from_numpy(mean).to(self.device)
        self._pca_projection = torch.from_numpy(projection).to(self.device)

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
        """PCA-whitened, L2-normalised descriptors ``float32 [N, dims]``; on the CPU in float64,
        rounded once (the same on every machine, see `locretrieval.models.published.vlad`)."""
        self._require_fitted()
        out = np.empty((len(vlads), self._pca_projection.shape[1]), dtype=np.float32)
        if self.device.type == "cpu":
            mean = self._pca_mean.numpy().astype(np.float64)
            projection = self._pca_projection.numpy().astype(np.float64)

            def whiten(start: int) -> None:
                whitened = (vlads[start : start + WHITENING_ROWS].astype(np.float64) - mean) @ projection
                norms = np.maximum(np.linalg.norm(whitened, axis=1, keepdims=True), EPS)
                out[start : start + WHITENING_ROWS] = whitened / norms

            # each chunk's product on one thread: the same sums whatever the thread count
            map_single_threaded(whiten, range(0, len(vlads), WHITENING_ROWS))
            return out
        for start in range(0, len(vlads), WHITENING_ROWS):
            chunk = torch.from_numpy(vlads[start : start + WHITENING_ROWS]).to(self.device)
            whitened = (chunk - self._pca_mean) @ self._pca_projection
            out[start : start + WHITENING_ROWS] = F.normalize(whitened, dim=-1).cpu().numpy()
        return out

    def describe(self, images: ImageSet) -> np.ndarray:
        """Descriptors of ``images``; the database seen by `fit` is not described twice."""
        self._require_fitted()
        if self._fitted_database is not None and self._fitted_database[0] == images.fingerprint(include_poses=False):
            return self._fitted_database[1].copy()
        return self._whiten(self._vlads(images))
