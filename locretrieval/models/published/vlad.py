"""VLAD (Jegou et al., CVPR 2010) as DenseVLAD uses it: a k-means vocabulary, hard assignment,
residual sums per visual word accumulated over descriptors added in chunks, intra-normalisation,
and a centred PCA whitening, each learned or applied on whole arrays.

On the CPU the vocabulary and the VLADs are the same on every machine, whatever its BLAS kernels,
vector width or thread count (a k-means amplifies a last-bit difference into another vocabulary):
word assignments go through float32 matrix products but are settled in float64
(`densevlad_kernels.assign_to_words`), and sums are float64 in a fixed order. The PCA and its
products are float64, rounded to float32 once: LAPACK's eigenvectors follow the machine's kernels
in their last float64 bits (more where eigenvalues nearly coincide), which moves a few float32
values by one unit (13 of the 2.1 million of the built-in scene's projection, between OpenBLAS's
Haswell and Sandybridge kernels; its rankings the same).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from locretrieval.models.published import densevlad_kernels as kernels
from locretrieval.models.published.densevlad_kernels import EPS as _EPS
from locretrieval.threads import map_single_threaded, single_threaded

#: Points assigned at a time in the k-means: their float32 word scores (2 MB) stay in cache.
KMEANS_CHUNK = 4096


def kmeans_vocabulary(points: np.ndarray, num_words: int, iterations: int, seed: int) -> np.ndarray:
    """``float32 [num_words, D]`` unit centroids of spherical k-means on ``points [N, D]``, every
    point used (no subsampling): centroids start at ``num_words`` distinct points drawn by numpy's
    generator seeded with ``seed``; each iteration assigns every point to its nearest centroid (largest
    dot product, the first on ties) and moves each centroid to its points' normalised sum. A word
    left without points restarts at a point drawn with ``[seed, iteration]``.

    By hand, because no library's k-means gives the same centroids on every machine (faiss's and
    scikit-learn's follow their BLAS kernels): each assignment is settled in float64 from a float32
    product and the sums are float64, per chunk of points in parallel threads
    (`densevlad_kernels.assign_to_words`), then over the chunks in their order."""
    points = np.ascontiguousarray(points, dtype=np.float32)
    rng = np.random.default_rng(seed)
    centroids = points[np.sort(rng.choice(len(points), num_words, replace=False))].astype(np.float64)
    kernels.normalize_rows(centroids)
    no_half_norms, keep = np.zeros(num_words), np.ones(KMEANS_CHUNK, dtype=bool)
    for iteration in range(iterations):
        words = centroids.astype(np.float32)

        def assign(start: int) -> tuple[np.ndarray, np.ndarray]:
            chunk = points[start : start + KMEANS_CHUNK]
            scores = chunk @ words.T
            sums, counts = np.zeros_like(centroids), np.zeros(num_words, dtype=np.int64)
            kernels.assign_to_words(chunk, scores, scores.argmax(1), words, no_half_norms, keep, sums, counts)
            return sums, counts

        chunks = map_single_threaded(assign, range(0, len(points), KMEANS_CHUNK))
        sums, counts = chunks[0]
        for chunk_sums, chunk_counts in chunks[1:]:  # in point order, whatever the thread count
            sums += chunk_sums
            counts += chunk_counts
        empty = np.flatnonzero(counts == 0)
        if len(empty):
            restarts = np.random.default_rng([seed, iteration]).choice(len(points), len(empty), replace=False)
            sums[empty] = points[restarts]
        kernels.normalize_rows(sums)
        centroids = sums
    return centroids.astype(np.float32)


def pca_whitening(vlads: np.ndarray, dim: int, regularization: float) -> tuple[np.ndarray, np.ndarray]:
    """``(mean [D], projection [D, dim])`` float32 of a centred PCA of ``vlads [N, D]`` whose
    component ``i`` is divided by ``sqrt(lambda_i + regularization * lambda_1)`` (bounding the gain
    of near-zero eigenvalues); ``dim`` at most ``N - 1``. In float64 (numpy's LAPACK), through the
    ``N x N`` Gram matrix when ``N <= D``; each component's sign makes its largest entry positive."""
    centred = np.array(vlads, dtype=np.float64)
    mean = centred.mean(axis=0)
    centred -= mean
    with single_threaded():  # a BLAS's threads would split its sums differently on every machine
        if len(centred) <= centred.shape[1]:
            eigenvalues, vectors = np.linalg.eigh(centred @ centred.T)
            eigenvalues, vectors = eigenvalues[::-1][:dim], vectors[:, ::-1][:, :dim]
            components = (centred.T @ vectors) / np.sqrt(np.maximum(eigenvalues, np.finfo(np.float64).tiny))
        else:
            eigenvalues, components = np.linalg.eigh(centred.T @ centred)
            eigenvalues, components = eigenvalues[::-1][:dim], components[:, ::-1][:, :dim]
    eigenvalues = eigenvalues / len(centred)
    if eigenvalues[0] <= 0:
        raise ValueError("DenseVLAD: all database VLADs are identical; PCA whitening is undefined")
    largest = np.abs(components).argmax(axis=0)
    components = components * np.sign(components[largest, np.arange(dim)])
    scale = 1.0 / np.sqrt(np.maximum(eigenvalues, 0.0) + regularization * eigenvalues[0])
    return mean.astype(np.float32), (components * scale).astype(np.float32)


class VladAccumulator:
    """Sums of residuals ``x - c_k`` per visual word over descriptors added in chunks.

    Hard assignment to the nearest centroid (largest ``x . c - |c|^2 / 2``, the first on ties);
    ``centroids [K, D]``. With ``cpu_kernels`` (default: on CPU) the scores are a matrix product
    per image and the numba kernel `densevlad_kernels.assign_to_words` settles each assignment in
    float64 (the same on every machine) and adds the descriptors up; otherwise torch, the whole
    batch at once (on a GPU: its own rounding).
    """

    def __init__(self, centroids: torch.Tensor, batch: int, cpu_kernels: bool | None = None) -> None:
        self.centroids = centroids
        self.batch = batch
        self.cpu_kernels = centroids.device.type == "cpu" if cpu_kernels is None else cpu_kernels
        self._centroids_t = centroids.T.contiguous()
        if self.cpu_kernels:
            self._half_norms = kernels.half_squared_norms(centroids.numpy())  # float64, in a fixed order
            self._neg_half_norms = torch.from_numpy(-self._half_norms).to(centroids.dtype)
        else:
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
                kernels.assign_to_words(
                    descriptors[image].numpy(),
                    scores.numpy(),
                    scores.numpy().argmax(1),
                    self.centroids.numpy(),
                    self._half_norms,
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
    """Intra-normalisation (L2 per word) then global L2: ``[B, K, D] -> [B, K * D]``; on the CPU
    by `densevlad_kernels.normalized_vlad` (float64, sums in a fixed order: the same everywhere)."""
    if residuals.device.type != "cpu":
        return F.normalize(F.normalize(residuals, dim=-1, eps=_EPS).flatten(1), dim=-1, eps=_EPS)
    out = residuals.new_empty(residuals.shape[0], residuals.shape[1] * residuals.shape[2])
    for blocks, vlad in zip(residuals.contiguous().numpy(), out.numpy()):
        kernels.normalized_vlad(blocks, vlad)
    return out
