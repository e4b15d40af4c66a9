"""VLAD (Jegou et al., CVPR 2010) as DenseVLAD uses it: a k-means vocabulary, hard assignment,
residual sums per visual word accumulated over descriptors added in chunks, intra-normalisation,
and a centred PCA whitening, each learned or applied on whole arrays.
"""

from __future__ import annotations

import math

import faiss
import numpy as np
import torch
import torch.nn.functional as F

from locretrieval.models.published import densevlad_kernels as kernels
from locretrieval.models.published.densevlad_kernels import EPS as _EPS
from locretrieval.threads import single_threaded


def kmeans_vocabulary(points: np.ndarray, num_words: int, iterations: int, seed: int) -> np.ndarray:
    """``[num_words, D]`` centroids of spherical k-means (faiss, seeded) on ``points [N, D]``, every
    point used (no subsampling)."""
    kmeans = faiss.Kmeans(
        points.shape[1],
        num_words,
        niter=iterations,
        seed=seed,
        spherical=True,
        max_points_per_centroid=math.ceil(len(points) / num_words),
    )
    with single_threaded():  # a threaded BLAS changes the assignments' last bits, then the centroids
        kmeans.train(np.ascontiguousarray(points, dtype=np.float32))
    return kmeans.centroids.copy()


def pca_whitening(vlads: np.ndarray, dim: int, regularization: float) -> tuple[np.ndarray, np.ndarray]:
    """``(mean [D], projection [D, dim])`` of a centred PCA (faiss) of ``vlads [N, D]`` whose
    component ``i`` is divided by ``sqrt(lambda_i + regularization * lambda_1)`` (bounding the gain
    of near-zero eigenvalues); ``dim`` at most ``N - 1``."""
    pca = faiss.PCAMatrix(vlads.shape[1], dim, 0.0, False)
    with single_threaded():  # the covariance and eigenvectors the same on any machine
        pca.train(np.ascontiguousarray(vlads, dtype=np.float32))
    eigenvalues = faiss.vector_to_array(pca.eigenvalues)[:dim].astype(np.float64)
    if eigenvalues[0] <= 0:
        raise ValueError("DenseVLAD: all database VLADs are identical; PCA whitening is undefined")
    components = faiss.vector_to_array(pca.PCAMat).reshape(-1, vlads.shape[1])[:dim]
    scale = 1.0 / np.sqrt(np.maximum(eigenvalues, 0.0) + regularization * eigenvalues[0])
    return faiss.vector_to_array(pca.mean).copy(), (components.T * scale).astype(np.float32)


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
