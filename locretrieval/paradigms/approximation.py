"""Paradigm 1, pose approximation (paper Sec. 3.1): interpolate the poses of the top-k images.

The query pose is ``P_q = sum_i w_i P_i`` over the top ``k`` database images, with weights
summing to one. A method is an `ApproximationMethod` chosen by ``_target_``
(``configs/paradigms/approximation/weights/``, ``paradigms.approximation.weights.<name>``); the built-in ones:

- `EqualWeights` (``ewb``): equal weights ``1/k``;
- `CosineSimilarityWeights` (``csi``): ``w_i ∝ (d_q . d_i)^alpha`` (cosine similarity of
  L2-normalised descriptors, read from the ranking's scores, which `search` sets to ``d_q . d_i``;
  clamped at 0 so that an even ``alpha`` cannot reward dissimilar images), the paper's ``alpha = 8``;
- `BarycentricWeights` (``bdi``): the weights minimising ``||d_q - sum_i w_i d_i||`` subject to
  ``sum_i w_i = 1`` (no sign constraint), in closed form ``w = G^-1 1 / (1^T G^-1 1)`` with
  ``G_ij = (d_i - d_q) . (d_j - d_q)``.

Camera centres are interpolated linearly; rotations are averaged as the dominant eigenvector
of ``sum_i w_i q_i q_i^T`` (sign-invariant), not as a renormalised sum. All k are processed
at once, queries a chunk at a time. ``bdi`` and ``csi`` need descriptors (`ApproximationMethod.uses_descriptors`),
so rankings without them (ground truth) get ``ewb`` only, as in the paper's Fig. 4.
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import scipy.linalg

from locretrieval import geometry
from locretrieval.config import named_parts, require
from locretrieval.estimates import LOCALIZED, PoseEstimates
from locretrieval.paradigms.base import Paradigm
from locretrieval.pool import resolve_workers
from locretrieval.retrieval import EMPTY, Ranking
from locretrieval.scene import ImageSet, Scene

log = logging.getLogger(__name__)

EMPTY_RETRIEVAL = "empty retrieval"
#: Relative ridge added to BDI's Gram matrix so duplicate descriptors split weights evenly.
BDI_RIDGE = 1e-9
DEGENERATE_BDI = "degenerate bdi weights"
#: Queries approximated together: every array of a chunk ([len(ks), q, K] at most) stays small.
CHUNK_QUERIES = 256
#: Largest table of database descriptor products `DescriptorProducts` forms at once.
PRODUCT_TABLE_BYTES = 1 << 28
#: A squared Cholesky pivot of a BDI Gram matrix built from float32 products below this share
#: of ``d_q . d_q`` (ill conditioned: rounding could move the weights by more than ~1e-6): that
#: query's Gram matrix is recomputed in float64. Measured: descriptors of neighbouring places
#: (scores ~0.6, pivots 0.35-0.45, benchmarks/bench_scale.py's RobotCar-size route) keep float32
#: products within 7.3e-7 of float64 at any threshold from 0.01 to 0.2; 0.5 sent them all to float64.
EXACT_GRAM_PIVOT = 0.1
#: Queries whose float64 Gram matrices are formed together (their ``[q, K + 1, D]`` float64 vectors stay small).
EXACT_CHUNK_QUERIES = 16
#: Largest difference between a descriptor ranking's score and ``d_q . d_i`` (`check_scores`).
SCORE_TOLERANCE = 1e-3


#: The centres ``[q, K, 3]`` and world-to-camera rotations ``[q, K, 4]`` (wxyz) of a chunk's ranked images.
Poses = tuple[np.ndarray, np.ndarray]


class ApproximationMethod(abc.ABC):
    """A pose-approximation method: the weights of the top-k database poses of each query (module
    docstring). ``uses_descriptors``: it reads the ranking's descriptors or its scores ``d_q . d_i``,
    so rankings without descriptors (ground truth, pairs files) skip it. A new one subclasses this
    (or `PrefixWeights`), in any package, and is chosen by its ``_target_``."""

    uses_descriptors: ClassVar[bool]

    def prepare(self, top: Ranking) -> Any:
        """What every chunk of ``top``'s queries reads, computed once per ranking (default: nothing)."""
        return None

    @abc.abstractmethod
    def poses(
        self, top: Ranking, rows: slice, valid: np.ndarray, ks: list[int], poses: Poses, prepared: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(qvec [len(ks), q, 4], tvec [len(ks), q, 3], failures [len(ks), q])`` of the queries
        ``rows`` of ``top`` from the ``poses`` of their ranked images (``valid [q, K]``: the slots
        holding one; a query has at least one): world-to-camera poses, through `interpolate` or
        `interpolate_prefixes`, and per k and query ``LOCALIZED`` or why the method failed."""


class PrefixWeights(ApproximationMethod):
    """A method that weighs each ranked image independently of k (`raw_weights`): the top-k weights
    are the first k, normalised, so one row serves every k (`interpolate_prefixes`)."""

    @abc.abstractmethod
    def raw_weights(self, scores: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """Unnormalised weights ``[q, K]`` from the ranking's ``scores [q, K]`` (0 on empty slots)."""

    def poses(
        self, top: Ranking, rows: slice, valid: np.ndarray, ks: list[int], poses: Poses, prepared: Any
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        qvec, tvec = interpolate_prefixes(self.raw_weights(top.scores[rows], valid), ks, *poses)
        return qvec, tvec, np.full((len(ks), len(valid)), LOCALIZED, dtype=object)


@dataclass
class EqualWeights(PrefixWeights):
    """EWB: equal weights ``1 / k``."""

    uses_descriptors: ClassVar[bool] = False

    def raw_weights(self, scores: np.ndarray, valid: np.ndarray) -> np.ndarray:
        return valid.astype(np.float64)


@dataclass
class CosineSimilarityWeights(PrefixWeights):
    """CSI: ``w_i ∝ (d_q . d_i)^alpha`` (``alpha`` positive; the paper: 8).

    Similarities are clamped at 0 and divided by the query's largest one before the power (the
    normalised weights are unchanged, and a large ``alpha`` cannot underflow them all); a query
    without a positive similarity gets equal weights.
    """

    alpha: float
    uses_descriptors: ClassVar[bool] = True

    def __post_init__(self) -> None:
        require(self.alpha > 0, "alpha", f"must be positive, got {self.alpha}")

    def raw_weights(self, scores: np.ndarray, valid: np.ndarray) -> np.ndarray:
        similarity = np.where(valid, np.clip(scores, 0.0, None), 0.0)  # descriptor rankings: d_q . d_i
        largest = similarity.max(axis=1, keepdims=True)
        dead = valid[:, 0] & (largest[:, 0] == 0)
        if dead.any():
            log.warning(
                "csi: %d queries with no positive similarity among their ranked images use equal weights", dead.sum()
            )
        with np.errstate(invalid="ignore", divide="ignore"):
            raw = (similarity / largest) ** self.alpha
        return np.where(dead[:, None], valid, np.where(valid, raw, 0.0))


@dataclass
class BarycentricWeights(ApproximationMethod):
    """BDI: the weights whose combination of the ranked descriptors is nearest the query's
    (`_bdi_weights`); a query whose Gram matrix cannot be solved fails (`DEGENERATE_BDI`)."""

    uses_descriptors: ClassVar[bool] = True

    def prepare(self, top: Ranking) -> DescriptorProducts:
        return DescriptorProducts(top)

    def poses(
        self, top: Ranking, rows: slice, valid: np.ndarray, ks: list[int], poses: Poses, prepared: DescriptorProducts
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        weights = _bdi_weights(_residual_gram_factors(top, rows, prepared), valid, ks)
        degenerate = ~np.isfinite(weights).all(-1)
        qvec, tvec = interpolate(np.where(degenerate[..., None], 0.0, weights), *poses)
        return qvec, tvec, np.where(degenerate, DEGENERATE_BDI, LOCALIZED).astype(object)


@dataclass
class PoseApproximation(Paradigm):
    """Paradigm 1 (``configs/paradigms/approximation.yaml``). ``methods``: the names of the methods
    computed, in this order, each a key of ``weights``: name -> `ApproximationMethod` (chosen by its
    ``_target_``; ``configs/paradigms/approximation/weights/``)."""

    methods: list[str]
    weights: dict[str, Any] = named_parts(ApproximationMethod)

    def __post_init__(self) -> None:
        super().__post_init__()
        unknown = [name for name in self.methods if name not in self.weights]
        require(
            bool(self.methods) and not unknown,
            "methods",
            f"must be a non-empty list of names of paradigms.approximation.weights {list(self.weights)}, "
            f"got {self.methods}",
        )

    def method_names(self) -> list[str]:
        return list(self.methods)

    def chosen(self) -> dict[str, ApproximationMethod]:
        """The methods computed, by name, in order."""
        return {name: self.weights[name] for name in self.methods}

    def run(self, scene: Scene, rankings: Sequence[Ranking], sfm: Any, cache_dir: Path | None) -> list[PoseEstimates]:
        """Every method for every ranking and every ``k`` (``sfm`` and ``cache_dir`` are unused:
        pose approximation needs no local features)."""
        return [
            estimate
            for ranking in rankings
            for estimate in approximate_poses(scene.database, ranking, self.k, self.chosen())
        ]


def approximate_poses(
    database: ImageSet, ranking: Ranking, ks: Sequence[int], methods: Mapping[str, ApproximationMethod]
) -> list[PoseEstimates]:
    """Pose estimates of every query for every k and method (name -> `ApproximationMethod`)
    applicable to ``ranking``.

    Each estimate is a world-to-camera pose (q wxyz, t). A query whose ranking is empty
    has no estimate (failure ``"empty retrieval"``); a query with fewer than ``k`` ranked
    images uses those it has. Queries are processed `CHUNK_QUERIES` at a time, chunks on one
    thread per core (numpy and LAPACK release the GIL).
    """
    ks = ranking.clamp_ks(ks)
    top = ranking.top(max(ks))
    applicable = {name: m for name, m in methods.items() if not m.uses_descriptors or ranking.has_descriptors}
    skipped = [name for name in methods if name not in applicable]
    if skipped:
        log.info("ranking %r has no descriptors: %s skipped, %s only", ranking.name, skipped, list(applicable))
    poses = (database.centers, database.qvec)
    chunks = [slice(start, start + CHUNK_QUERIES) for start in range(0, top.num_queries, CHUNK_QUERIES)]
    results = []
    with ThreadPoolExecutor(max(1, min(resolve_workers(None), len(chunks)))) as pool:
        for name, method in applicable.items():
            chunk_estimates = partial(_approximate_chunk, method, top, ks=ks, poses=poses, prepared=method.prepare(top))
            parts = list(pool.map(chunk_estimates, chunks))
            qvec, tvec, failures = (np.concatenate(arrays, axis=1) for arrays in zip(*parts))
            results.append(PoseEstimates(ranking.name, ranking.kind, "approximation", name, ks, qvec, tvec, failures))
    return results


def _approximate_chunk(
    method: ApproximationMethod,
    top: Ranking,
    rows: slice,
    ks: list[int],
    poses: tuple[np.ndarray, np.ndarray],
    prepared: Any,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(qvec [len(ks), q, 4], tvec [len(ks), q, 3], failures [len(ks), q])`` of the queries ``rows``."""
    indices = top.indices[rows]
    valid = indices != EMPTY
    safe = np.where(valid, indices, 0)
    failures = np.where(valid[:, 0][None, :].repeat(len(ks), 0), LOCALIZED, EMPTY_RETRIEVAL).astype(object)
    qvec, tvec, failed = method.poses(top, rows, valid, ks, (poses[0][safe], poses[1][safe]), prepared)
    failures = np.where(failures == LOCALIZED, failed, failures)
    qvec[failures != LOCALIZED] = np.nan
    tvec[failures != LOCALIZED] = np.nan
    return qvec, tvec, failures


def _bdi_weights(factors: np.ndarray, valid: np.ndarray, ks: list[int]) -> np.ndarray:
    """Barycentric descriptor interpolation weights ``[len(ks), q, K]`` in closed form from the
    Cholesky factors ``L [q, K, K]`` of the residual Gram matrices (`_residual_gram_factors`).

    ``w_k ∝ G_k^-1 1`` where ``G_k`` is the leading ``k x k`` block of ``G``. With ``G = L L^T``
    (Cholesky) and ``M = L^-1``, the leading blocks of ``L`` and ``M`` are the factors of
    ``G_k``, so ``G_k^-1 1 = M_k^T (M_k 1)`` and its j-th entry is ``sum_{i<k} M_ij y_i`` with
    ``y = M 1``: a cumulative sum over i gives every k at once. A query with fewer ranked
    images uses all it has; one without ranked images, or whose weights are not finite, gets
    non-finite weights.
    """
    count, depth = valid.shape
    mask = (np.arange(depth)[None, :] < np.asarray(ks)[:, None])[:, None, :] & valid[None]
    failed = ~np.isfinite(factors).all((1, 2))
    factors = np.where(failed[:, None, None], np.eye(depth), factors)
    inverse_factor = scipy.linalg.inv(factors, assume_a="lower triangular", check_finite=False)  # M
    inverse_factor[failed] = np.nan
    y = inverse_factor.sum(-1)  # M 1
    partial = np.cumsum(inverse_factor * y[:, :, None], axis=1)  # [q, i, j]: sum_{i'<=i} M_i'j y_i'
    lengths = mask.sum(-1)  # [len(ks), q]: min(k, ranked images)
    rows = np.clip(lengths - 1, 0, None)
    solution = np.where(mask, partial[np.arange(count)[None], rows], 0.0)
    total = solution.sum(-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return solution / total


class DescriptorProducts:
    """``d_i . d_j`` of the database images a ranking holds, looked up per query.

    When few distinct images are ranked (``m^2 <= Q K^2`` and the ``m x m`` table fits
    `PRODUCT_TABLE_BYTES`), one matrix product of their descriptors serves every query;
    otherwise each chunk gathers its queries' ``[q, K, D]`` descriptors and multiplies them.
    Products are in the descriptors' precision (float32 for `search` rankings).
    """

    def __init__(self, top: Ranking) -> None:
        self.descriptors = top.database_descriptors
        used = np.unique(top.indices[top.indices != EMPTY])
        small = len(used) ** 2 <= top.num_queries * top.depth**2
        if small and len(used) ** 2 * self.descriptors.itemsize <= PRODUCT_TABLE_BYTES:
            self.position = np.zeros(len(self.descriptors), dtype=np.int64)
            self.position[used] = np.arange(len(used))
            chosen = self.descriptors[used]
            with np.errstate(invalid="ignore", over="ignore"):  # non-finite descriptors: their queries fail
                self.table = chosen @ chosen.T
        else:
            self.table = None

    def __call__(self, indices: np.ndarray) -> np.ndarray:
        """``[q, K, K]`` products of the database images ``indices [q, K]`` (no ``EMPTY``)."""
        if self.table is not None:
            position = self.position[indices]
            return np.take(self.table.ravel(), position[:, :, None] * len(self.table) + position[:, None, :])
        gathered = self.descriptors[indices]
        return gathered @ gathered.transpose(0, 2, 1)


def _residual_gram_factors(top: Ranking, rows: slice, products: DescriptorProducts) -> np.ndarray:
    """Cholesky factors ``L [q, K, K]`` of the residual Gram matrices of the queries ``rows``,
    ``G_ij = (d_i - d_q) . (d_j - d_q) = d_i . d_j - s_i - s_j + d_q . d_q`` over their ranked
    images, with the ranking's scores ``s_i = d_q . d_i`` (`check_scores`); NaN where ``G`` is
    not positive definite or not finite.

    Rows and columns of empty slots are those of the identity, so they never mix with filled
    slots (which always come first). A ridge of ``BDI_RIDGE * max(trace(G) / K, 1)`` keeps
    duplicated descriptors solvable (they share the weight equally). Where the products'
    rounding (float32 descriptors: ~1e-7) could move the weights, i.e. where a squared Cholesky
    pivot is below `EXACT_GRAM_PIVOT` times ``d_q . d_q`` or the factorisation fails, the
    query's ``G`` is computed in float64 (`_exact_grams`).
    """
    indices = top.indices[rows]
    valid = indices != EMPTY
    safe = np.where(valid, indices, 0)
    queries = top.query_descriptors[rows].astype(np.float64)
    scores = top.scores[rows].astype(np.float64)
    check_scores(top.name, products.descriptors[safe[:, 0]], queries, scores[:, 0], valid[:, 0])
    pair = valid[:, :, None] & valid[:, None, :]
    grams = products(safe).astype(np.float64)
    squared_norms = np.einsum("qd,qd->q", queries, queries)
    with np.errstate(invalid="ignore"):  # non-finite descriptors: NaN, their factorisation fails
        grams -= scores[:, :, None] + scores[:, None, :] - squared_norms[:, None, None]
    factors = _cholesky(_with_ridge(np.where(pair, grams, np.eye(top.depth))))
    pivots = np.diagonal(factors, axis1=1, axis2=2) ** 2
    exact = np.flatnonzero(~(pivots.min(-1) >= EXACT_GRAM_PIVOT * squared_norms))
    for start in range(0, len(exact), EXACT_CHUNK_QUERIES):
        part = exact[start : start + EXACT_CHUNK_QUERIES]
        exact_grams = _exact_grams(products.descriptors[safe[part]], queries[part])
        factors[part] = _cholesky(_with_ridge(np.where(pair[part], exact_grams, np.eye(top.depth))))
    return factors


def _exact_grams(ranked: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Residual Gram matrices ``[q, K, K]`` of ranked descriptors ``[q, K, D]`` and their queries
    ``[q, D]`` in float64: one product of the ``K + 1`` vectors gives ``d_i . d_j``, ``d_i . d_q``
    and ``d_q . d_q``, whose float64 rounding (~1e-16) the cancellation cannot amplify."""
    depth = ranked.shape[1]
    vectors = np.empty((len(queries), depth + 1, queries.shape[1]))
    vectors[:, :depth], vectors[:, depth] = ranked, queries
    with np.errstate(invalid="ignore", over="ignore"):
        products = vectors @ vectors.transpose(0, 2, 1)
        scores = products[:, :depth, depth]
        return (
            products[:, :depth, :depth]
            - scores[:, :, None]
            - scores[:, None, :]
            + products[:, depth, depth][:, None, None]
        )


def _with_ridge(grams: np.ndarray) -> np.ndarray:
    depth = grams.shape[-1]
    scale = np.trace(grams, axis1=1, axis2=2) / depth
    grams[:, np.arange(depth), np.arange(depth)] += BDI_RIDGE * np.maximum(scale, 1.0)[:, None]
    return grams


def _cholesky(matrices: np.ndarray) -> np.ndarray:
    """Lower Cholesky factors ``[n, K, K]``; NaN for a matrix that is not positive definite."""
    try:
        return np.linalg.cholesky(matrices)
    except np.linalg.LinAlgError:  # at least one of them: factor each
        factors = np.full_like(matrices, np.nan)
        for n, matrix in enumerate(matrices):
            try:
                factors[n] = np.linalg.cholesky(matrix)
            except np.linalg.LinAlgError:
                pass
        return factors


def check_scores(name: str, first: np.ndarray, queries: np.ndarray, scores: np.ndarray, valid: np.ndarray) -> None:
    """Raise unless each query's score of its first ranked image is ``d_q . d_1`` (`Ranking`'s
    contract for descriptor rankings, which BDI's Gram matrices rely on)."""
    products = np.einsum("qd,qd->q", queries, first.astype(np.float64))
    off = valid & np.isfinite(products) & (np.abs(products - scores) > SCORE_TOLERANCE)
    if off.any():
        query = int(np.flatnonzero(off)[0])
        raise ValueError(
            f"ranking {name!r}: {off.sum()} queries' scores are not the descriptors' inner products "
            f"(e.g. query {query}: score {scores[query]:.6f}, d_q . d_i = {products[query]:.6f}); "
            "BDI needs scores equal to d_q . d_i, as `search` returns them"
        )


def interpolate(weights: np.ndarray, centers: np.ndarray, rotations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera poses ``([len(ks), Q, 4], [len(ks), Q, 3])`` from per-k weights ``[len(ks), Q, K]``."""
    center = (weights[..., None, :] @ centers)[..., 0, :]  # [len(ks), Q, 1, K] @ [Q, K, 3]
    qvec = geometry.average_quaternions(rotations, weights)
    return qvec, geometry.translations_from_centers(qvec, center)


def interpolate_prefixes(
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
