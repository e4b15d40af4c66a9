"""Paradigm 1, pose approximation (paper Sec. 3.1): interpolate the poses of the top-k images.

The query pose is ``P_q = sum_i w_i P_i`` over the top ``k`` database images, with weights
summing to one:

- ``ewb``: equal weights ``1/k``;
- ``csi``: ``w_i ∝ (d_q . d_i)^alpha`` (cosine similarity of L2-normalised descriptors, read
  from the ranking's scores, which `search` sets to ``d_q . d_i``; clamped at 0 so that an
  even ``alpha`` cannot reward dissimilar images), ``alpha = 8``;
- ``bdi``: the weights minimising ``||d_q - sum_i w_i d_i||`` subject to ``sum_i w_i = 1``
  (no sign constraint), in closed form ``w = G^-1 1 / (1^T G^-1 1)`` with
  ``G_ij = (d_i - d_q) . (d_j - d_q)``.

Camera centres are interpolated linearly; rotations are averaged as the dominant eigenvector
of ``sum_i w_i q_i q_i^T`` (sign-invariant), not as a renormalised sum. All queries and all
k are processed at once. ``bdi`` and ``csi`` need descriptors, so rankings without them
(ground truth) get ``ewb`` only, as in the paper's Fig. 4.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from locretrieval import geometry
from locretrieval.config import require
from locretrieval.localization.estimates import LOCALIZED, PoseEstimates
from locretrieval.localization.paradigm import ParadigmSettings
from locretrieval.retrieval import EMPTY, Ranking
from locretrieval.scene import ImageSet, Scene

log = logging.getLogger(__name__)

METHODS = ("ewb", "bdi", "csi")
DESCRIPTOR_METHODS = ("bdi", "csi")
EMPTY_RETRIEVAL = "empty retrieval"
#: Relative ridge added to BDI's Gram matrix so duplicate descriptors split weights evenly.
BDI_RIDGE = 1e-9
DEGENERATE_BDI = "degenerate bdi weights"
#: Bytes of gathered database descriptors held at once when forming BDI Gram matrices.
GATHER_CHUNK_BYTES = 1 << 28


@dataclass
class ApproximationSettings(ParadigmSettings):
    """``methods``: any of `METHODS`; ``alpha``: the CSI exponent (the paper: 8)."""

    methods: list[str]
    alpha: float

    def __post_init__(self) -> None:
        super().__post_init__()
        unknown = sorted(set(self.methods) - set(METHODS))
        require(bool(self.methods) and not unknown, "methods", f"must be a non-empty list of {list(METHODS)}, got {self.methods}")
        require(self.alpha > 0, "alpha", f"must be positive, got {self.alpha}")


def run(
    scene: Scene, rankings: Sequence[Ranking], settings: ApproximationSettings, sfm: Any = None, cache_dir: Path | None = None
) -> list[PoseEstimates]:
    """Paradigm entry point: every method for every ranking and every ``settings.k`` (``sfm`` and
    ``cache_dir`` are unused: pose approximation needs no local features)."""
    return [
        estimate
        for ranking in rankings
        for estimate in approximate_poses(scene.database, ranking, settings.k, settings.methods, settings.alpha)
    ]


def approximate_poses(
    database: ImageSet, ranking: Ranking, ks: Sequence[int], methods: Sequence[str], alpha: float
) -> list[PoseEstimates]:
    """Pose estimates of every query for every k and method applicable to ``ranking``.

    Each estimate is a world-to-camera pose (q wxyz, t). A query whose ranking is empty
    has no estimate (failure ``"empty retrieval"``); a query with fewer than ``k`` ranked
    images uses those it has.
    """
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown pose approximation methods {sorted(unknown)}; expected {METHODS}")
    ks = ranking.clamp_ks(ks)
    top = ranking.top(max(ks))
    valid = top.indices != EMPTY
    safe = np.where(valid, top.indices, 0)
    centers = database.centers[safe]
    rotations = database.qvec[safe]

    applicable = [m for m in methods if m not in DESCRIPTOR_METHODS or ranking.has_descriptors]
    skipped = [m for m in methods if m not in applicable]
    if skipped:
        log.info("ranking %r has no descriptors: %s skipped, %s only", ranking.name, skipped, applicable)

    results = []
    for method in applicable:
        failures = np.where(valid[:, 0][None, :].repeat(len(ks), 0), LOCALIZED, EMPTY_RETRIEVAL).astype(object)
        if method == "bdi":
            weights = _bdi_weights(top, valid, ks)
            degenerate = ~np.isfinite(weights).all(-1)
            failures[degenerate & (failures == LOCALIZED)] = DEGENERATE_BDI
            qvec, tvec = _interpolate(np.where(degenerate[..., None], 0.0, weights), centers, rotations)
        else:
            qvec, tvec = _interpolate_prefixes(_prefix_weights(method, top, valid, alpha), ks, centers, rotations)
        qvec[failures != LOCALIZED] = np.nan
        tvec[failures != LOCALIZED] = np.nan
        results.append(PoseEstimates(ranking.name, ranking.kind, "approximation", method, ks, qvec, tvec, failures))
    return results


def _prefix_weights(method: str, top: Ranking, valid: np.ndarray, alpha: float) -> np.ndarray:
    """Unnormalised weights ``[Q, K]`` whose first k entries, normalised, are the top-k weights.

    EWB and CSI weigh each image independently of k, so one row serves every k. CSI
    similarities are clamped at 0 and divided by the query's largest one before the power
    (the normalised weights are unchanged, and a large ``alpha`` cannot underflow them all);
    a query without a positive similarity gets equal weights.
    """
    if method == "ewb":
        return valid.astype(np.float64)
    similarity = np.where(valid, np.clip(top.scores, 0.0, None), 0.0)  # descriptor rankings: d_q . d_i
    largest = similarity.max(axis=1, keepdims=True)
    dead = valid[:, 0] & (largest[:, 0] == 0)
    if dead.any():
        log.warning("csi: %d queries with no positive similarity among their ranked images use equal weights", dead.sum())
    with np.errstate(invalid="ignore", divide="ignore"):
        raw = (similarity / largest) ** alpha
    return np.where(dead[:, None], valid, np.where(valid, raw, 0.0))


def _bdi_weights(top: Ranking, valid: np.ndarray, ks: list[int]) -> np.ndarray:
    """Barycentric descriptor interpolation weights ``[len(ks), Q, K]`` in closed form.

    ``w_k ∝ G_k^-1 1`` where ``G_k`` is the leading ``k x k`` block of the residual Gram
    matrix ``G``. With ``G = L L^T`` (Cholesky) and ``M = L^-1``, the leading blocks of ``L``
    and ``M`` are the factors of ``G_k``, so ``G_k^-1 1 = M_k^T (M_k 1)`` and its j-th entry
    is ``sum_{i<k} M_ij y_i`` with ``y = M 1``: a cumulative sum over i gives every k at once.
    A ridge of ``BDI_RIDGE * max(trace(G) / K, 1)`` keeps duplicated descriptors solvable
    (they share the weight equally). A query with fewer ranked images uses all it has; one
    without ranked images, or whose weights are still not finite, gets non-finite weights.
    """
    mask = (np.arange(top.depth)[None, :] < np.asarray(ks)[:, None])[:, None, :] & valid[None]
    gram = _residual_grams(top)  # [Q, K, K], identity on empty slots
    depth = top.depth
    scale = np.trace(gram, axis1=1, axis2=2) / depth
    gram[:, np.arange(depth), np.arange(depth)] += BDI_RIDGE * np.maximum(scale, 1.0)[:, None]
    inverse_factor = np.linalg.inv(np.linalg.cholesky(gram))  # M, lower triangular
    y = inverse_factor.sum(-1)  # M 1
    partial = np.cumsum(inverse_factor * y[:, :, None], axis=1)  # [Q, i, j]: sum_{i'<=i} M_i'j y_i'
    lengths = mask.sum(-1)  # [len(ks), Q]: min(k, ranked images)
    rows = np.clip(lengths - 1, 0, None)
    solution = np.where(mask, partial[np.arange(top.num_queries)[None], rows], 0.0)
    total = solution.sum(-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return solution / total


def _residual_grams(top: Ranking) -> np.ndarray:
    """``G_ij = (d_i - d_q) . (d_j - d_q)`` over each query's ranked images, ``[Q, K, K]``.

    Rows and columns of empty slots are those of the identity, so they never mix with
    filled slots (which always come first).
    """
    grams = np.empty((top.num_queries, top.depth, top.depth), dtype=np.float64)
    for rows, gathered, query in _gathered_descriptors(top):
        residuals = gathered - query[:, None, :]
        grams[rows] = residuals @ residuals.transpose(0, 2, 1)
    valid = top.indices != EMPTY
    pair = valid[:, :, None] & valid[:, None, :]
    return np.where(pair, grams, np.eye(top.depth)[None])


def _gathered_descriptors(top: Ranking):
    """Yield ``(rows, database descriptors [q, K, D], query descriptors [q, D])`` per chunk.

    Chunks keep the gathered float64 block under ``GATHER_CHUNK_BYTES``; empty slots gather
    database image 0 and must be masked by the caller.
    """
    indices = np.where(top.indices != EMPTY, top.indices, 0)
    per_query = max(1, top.depth * top.database_descriptors.shape[1] * 8)
    size = max(1, GATHER_CHUNK_BYTES // per_query)
    for start in range(0, top.num_queries, size):
        rows = slice(start, start + size)
        yield (
            rows,
            top.database_descriptors[indices[rows]].astype(np.float64),
            top.query_descriptors[rows].astype(np.float64),
        )


def _interpolate(
    weights: np.ndarray, centers: np.ndarray, rotations: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera poses ``([len(ks), Q, 4], [len(ks), Q, 3])`` from per-k weights ``[len(ks), Q, K]``."""
    center = (weights[..., None, :] @ centers)[..., 0, :]  # [len(ks), Q, 1, K] @ [Q, K, 3]
    qvec = geometry.average_quaternions(rotations, weights)
    return qvec, geometry.translations_from_centers(qvec, center)


def _interpolate_prefixes(
    raw: np.ndarray, ks: list[int], centers: np.ndarray, rotations: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Poses for weights proportional to ``raw[:, :k]`` for each k, by cumulative sums over slots."""
    at = np.asarray(ks) - 1
    total = np.cumsum(raw, axis=1)[:, at]  # [Q, len(ks)]
    weighted_centers = np.cumsum(raw[..., None] * centers, axis=1)[:, at]
    moments = np.cumsum(raw[..., None] * geometry.quaternion_outer_products(rotations), axis=1)[:, at]
    with np.errstate(invalid="ignore", divide="ignore"):
        center = (weighted_centers / total[..., None]).transpose(1, 0, 2)
    qvec = geometry.dominant_quaternion(moments.transpose(1, 0, 2))
    return qvec, geometry.translations_from_centers(qvec, center)
