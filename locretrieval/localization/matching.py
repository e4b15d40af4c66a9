"""Local feature matching between image pairs, geometric verification, and per-pair caches.

Matching is mutual nearest neighbours with Lowe's ratio test on L2-normalised descriptors
(`NearestNeighbourMatcher`: torch, on the CPU or a GPU, one block of the similarity matrix at a
time). Matches ``int32 [m, 2]`` hold keypoint indices (first image, second image).

Verification (``ensure(..., verification=...)``, then ``load(..., verification=...)``):

- ``"none"``: the raw matches;
- ``"poses"``: both images have known poses: matches whose Sampson error against the
  pose-derived essential matrix (undistorted coordinates, scaled to pixels by the mean focal
  length) is at most ``max_epipolar_error`` pixels. Exact and cheap, no RANSAC: used for
  database pairs (and query-database pairs of the co-observation ground truth);
- ``"two_view"``: pycolmap's two-view geometry estimation (RANSAC on E, F and H), for
  query-database pairs when ``query_verification: two_view``. It costs ~30 ms per pair here,
  ten times the matching, and PnP's RANSAC rejects the same outliers, so it is off by default.

Caches, all `ShardedStore`s filled by worker processes:
``<cache_dir>/matches/<features 0>--<features 1>--<ratio and precision key>/`` (raw matches, keyed by the
pair of image names) and ``...--poses-<key>/``, ``...--two-view-<key>/`` (verified matches).
A pair is matched once whatever k or verification needed it, and a database pair once in
either order.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from itertools import groupby
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.cache import config_key
from locretrieval.config import require
from locretrieval.localization.features import FeatureStore
from locretrieval.localization.store import ShardedStore
from locretrieval.localization.workers import parallel_map, resolve_workers
from locretrieval.scene import Camera, ImageSet

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

VERIFICATIONS = ("none", "poses", "two_view")
#: pycolmap two-view configurations whose inliers follow a scene geometry; the others are
#: undefined, degenerate, a watermark (a fixed image overlay) or several motions.
GEOMETRIC_CONFIGURATIONS = ("CALIBRATED", "UNCALIBRATED", "PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC")
#: Pairs per worker task (one shard of the cache).
PAIRS_PER_SHARD = 512
#: Bytes of one block of similarities on a CPU: reduced while it is in the last-level cache.
CPU_BLOCK_BYTES = 8 << 20
#: Bytes of one block of similarities on a GPU (bounded memory, long enough kernels).
CUDA_BLOCK_BYTES = 1 << 30
#: Width of the column tiles through which each row's best column is found, and height of the
#: groups of rows through which each column's is.
TILE = 128
#: Floating-point types of the similarities.
PRECISIONS = ("float32", "float16")
#: Smallest norm a descriptor is divided by (zero rows stay zero).
NORM_EPSILON = 1e-12
#: Bump when the meaning of cached matches changes.
CACHE_VERSION = 1

Pair = tuple[str, str]


@dataclass
class TwoViewSettings:
    """pycolmap two-view geometry of query pairs: RANSAC ``max_error`` px, ``min_num_inliers``."""

    max_error: float
    min_num_inliers: int

    def __post_init__(self) -> None:
        require(self.max_error > 0, "max_error", f"must be a positive number of pixels, got {self.max_error}")
        require(self.min_num_inliers >= 5, "min_num_inliers", f"must be >= 5 (a minimal sample), got {self.min_num_inliers}")


@dataclass
class MatchingSettings:
    """Mutual nearest neighbours with Lowe's ``ratio`` test (1: off); database pairs verified
    against their known poses (Sampson error below ``max_epipolar_error`` px); query pairs
    verified per ``query_verification`` (``none``: PnP RANSAC only, or ``two_view``).
    The matcher (`NearestNeighbourMatcher`) runs on ``device`` (``auto``: CUDA when there is a
    GPU) with ``precision`` similarities in blocks of ``block_mib`` MiB (null: `CPU_BLOCK_BYTES`
    on a CPU, on a GPU `CUDA_BLOCK_BYTES` or a quarter of each worker's share of its memory)."""

    ratio: float
    max_epipolar_error: float
    query_verification: str
    two_view: TwoViewSettings
    device: str
    precision: str
    block_mib: float | None

    def __post_init__(self) -> None:
        require(0 < self.ratio <= 1, "ratio", f"must be in (0, 1], got {self.ratio}")
        require(self.max_epipolar_error > 0, "max_epipolar_error", f"must be a positive number of pixels, got {self.max_epipolar_error}")
        require(self.query_verification in ("none", "two_view"), "query_verification",
                f"must be 'none' or 'two_view', got {self.query_verification!r}")
        require(self.device == "auto" or self.device.split(":")[0] in ("cpu", "cuda"), "device",
                f"must be auto, cpu or cuda[:N], got {self.device!r}")
        require(self.precision in PRECISIONS, "precision", f"must be one of {list(PRECISIONS)}, got {self.precision!r}")
        require(self.block_mib is None or self.block_mib > 0, "block_mib", f"must be a positive number of MiB or null, got {self.block_mib}")

    def identity(self) -> dict[str, Any]:
        """What determines the matches (not where or in which blocks they are computed)."""
        settings = dataclasses.asdict(self)
        return {key: settings[key] for key in ("ratio", "max_epipolar_error", "query_verification", "two_view", "precision")}

    def matcher(self, workers: int = 1) -> NearestNeighbourMatcher:
        """The matcher of these settings in a process that is one of ``workers`` sharing the
        device. On a GPU, a worker process caps its memory at ``1 / (workers + 1)``
        (`torch.cuda.set_per_process_memory_fraction`), leaving a share to the main process, which
        is never capped (it matches small workloads itself and holds a network in training)."""
        import multiprocessing

        from locretrieval.device import resolve_device

        device = resolve_device(self.device)
        block_bytes = CPU_BLOCK_BYTES if self.block_mib is None else int(self.block_mib * 2**20)
        if device.type == "cuda":
            import torch

            # a worker's share leaves one for the main process (which holds a network in training)
            share = 1.0 / (max(1, workers) + 1) if multiprocessing.parent_process() is not None else 1.0
            if share < 1.0:
                torch.cuda.set_per_process_memory_fraction(share, device.index if device.index is not None else torch.cuda.current_device())
            if self.block_mib is None:
                block_bytes = min(CUDA_BLOCK_BYTES, int(share * torch.cuda.get_device_properties(device).total_memory / 4))
        return NearestNeighbourMatcher(self.ratio, str(device), self.precision, block_bytes)


def pair_key(pair: Pair) -> str:
    return f"{pair[0]}\n{pair[1]}"


# ------------------------------------------------------------------------------------ matching


def normalized_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """Float32 rows of unit L2 norm (zero rows stay zero)."""
    values = np.asarray(descriptors, dtype=np.float32)
    return values / np.maximum(np.linalg.norm(values, axis=1, keepdims=True), NORM_EPSILON)


@dataclass(frozen=True)
class NearestNeighbourMatcher:
    """Mutual nearest neighbours with Lowe's ratio test, in torch on ``device``.

    The similarity matrix of a pair is computed one block at a time, about square, of
    ``block_bytes`` (on a CPU small enough to be reduced while it is in cache, which also keeps
    the matrix product as fast as one whole product; on a GPU, bounded memory). Each block
    updates running per-row and per-column state, so nothing of the size of the matrix is kept:

    - per row: the best and second-best values and the best column, found through the maxima
      of column tiles of `TILE` (``amax``, one vectorised pass: ``argmax`` over a long
      row is several times slower on a CPU) and merged with the earlier blocks of the row;
    - per column: the best value in each group of `TILE` rows (``amax`` again). A row's best
      column is a mutual match only if that column's best value is the row's and first reached
      in the row's group; only for those candidates is the column's first best row in the
      group found, from their similarities recomputed (each candidate's column with its group's
      rows: at most ``TILE / columns`` of the whole product).

    Ties go to the lowest index both ways, as numpy's ``argmax``; a tie for the best value makes
    the second-best equal to it. (The recomputed candidate similarities may round differently from
    the blocked product: two rows within one rounding step of each other for a column can then
    be ordered differently; exact ties, as the tests use, cannot.) ``precision``: ``float32``, or ``float16`` similarities
    (for GPUs; the README says how often it changes a match).
    """

    ratio: float
    device: str = "cpu"
    precision: str = "float32"
    block_bytes: int = CPU_BLOCK_BYTES

    def __post_init__(self) -> None:
        require(0 < self.ratio <= 1, "ratio", f"must be in (0, 1], got {self.ratio}")
        require(self.precision in PRECISIONS, "precision", f"must be one of {list(PRECISIONS)}, got {self.precision!r}")
        require(self.block_bytes >= 4 * TILE**2, "block_bytes", f"must hold {TILE} x {TILE} float32 similarities, got {self.block_bytes}")

    def __call__(self, first: np.ndarray, others: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Matches ``int32 [m, 2]`` (row in ``first``, row in the other) with each of ``others``."""
        import torch

        dtype = getattr(torch, self.precision)
        query = torch.from_numpy(normalized_descriptors(first)).to(self.device, dtype)
        return [self._match(query, torch.from_numpy(normalized_descriptors(other)).to(self.device, dtype)) for other in others]

    def block_shape(self, rows: int, columns: int, element_size: int) -> tuple[int, int]:
        """Rows (all, or a multiple of `TILE`) and columns (a multiple of `TILE`) of the blocks
        of similarities: about square, at most ``block_bytes``, of equal sizes."""
        tiles = -(-columns // TILE)
        column_blocks = -(-tiles // max(1, int((self.block_bytes / element_size) ** 0.5) // TILE))
        width = -(-tiles // column_blocks) * TILE
        max_height = self.block_bytes // (width * element_size) // TILE * TILE
        if rows <= max_height:
            return rows, width
        return -(-rows // -(-rows // max_height) // TILE) * TILE, width

    def _match(self, query: "torch.Tensor", partner: "torch.Tensor") -> np.ndarray:
        import torch

        rows, columns = len(query), len(partner)
        if not rows or not columns:
            return np.empty((0, 2), dtype=np.int32)
        height, width = self.block_shape(rows, columns, query.element_size())
        state = _BestValues(rows, columns, query)
        buffer = torch.empty((height, width), device=query.device, dtype=query.dtype)  # reused: no page faults
        for first_column in range(0, columns, width):
            tile = torch.zeros((query.shape[1], width), device=query.device, dtype=query.dtype)
            valid = min(width, columns - first_column)
            tile[:, :valid] = partner[first_column : first_column + valid].T
            for first_row in range(0, rows, height):
                stop = min(rows, first_row + height)
                similarity = torch.mm(query[first_row:stop], tile, out=buffer[: stop - first_row])
                similarity[:, valid:] = -torch.inf
                state.update(similarity, first_row, first_column, valid)
        mutual = state.mutual(query, partner).cpu().numpy()
        best, second = state.row_best.float().cpu().numpy(), state.row_second.float().cpu().numpy()
        # squared distances of unit vectors: 2 - 2 s
        passes = np.maximum(2 - 2 * best, 0) <= self.ratio**2 * np.maximum(2 - 2 * second, 0) if columns >= 2 else np.ones(rows, dtype=bool)
        keep = passes & mutual
        return np.column_stack([np.flatnonzero(keep), state.row_argmax.cpu().numpy()[keep]]).astype(np.int32)


class _BestValues:
    """Running best values of the rows (best, second best, first best column) and the best value
    of each column in each group of `TILE` rows, of a similarity matrix seen a block at a time."""

    def __init__(self, rows: int, columns: int, like: "torch.Tensor") -> None:
        import torch

        def full(shape: tuple[int, ...], value: float, dtype: "torch.dtype" = like.dtype) -> "torch.Tensor":
            return torch.full(shape, value, device=like.device, dtype=dtype)

        self.row_best, self.row_second, self.row_argmax = full((rows,), -torch.inf), full((rows,), -torch.inf), full((rows,), 0, torch.int64)
        self.column_best = full((-(-rows // TILE), columns), -torch.inf)  # [group of rows, column]

    def update(self, similarity: "torch.Tensor", first_row: int, first_column: int, valid: int) -> None:
        """Merge one block: rows from ``first_row`` (a multiple of `TILE`; fewer than a multiple
        of `TILE` rows only in the last block), columns from ``first_column``, of which the
        first ``valid`` are real (the rest: -inf padding)."""
        import torch

        group, columns, whole = first_row // TILE, slice(first_column, first_column + valid), len(similarity) // TILE
        if whole:
            self.column_best[group : group + whole, columns] = similarity[: whole * TILE].view(whole, TILE, -1).amax(1)[:, :valid]
        if whole * TILE < len(similarity):
            self.column_best[group + whole, columns] = similarity[whole * TILE :].amax(0)[:valid]
        rows = slice(first_row, first_row + len(similarity))
        best, second, argmax = _row_best_two(similarity)
        old_best = self.row_best[rows]
        self.row_second[rows] = torch.maximum(torch.maximum(self.row_second[rows], second), torch.minimum(old_best, best))
        self.row_argmax[rows] = torch.where(best > old_best, argmax + first_column, self.row_argmax[rows])
        self.row_best[rows] = torch.maximum(old_best, best)

    def mutual(self, query: "torch.Tensor", partner: "torch.Tensor") -> "torch.Tensor":
        """Boolean ``[rows]``: the row is its best column's first best row (``query``, ``partner``:
        the descriptors whose products the blocks held)."""
        import torch

        column_best = self.column_best.amax(0)
        first_group = _first_equal(self.column_best.T, column_best)
        group = torch.arange(len(self.row_best), device=query.device) // TILE
        candidate = (self.row_best == column_best[self.row_argmax]) & (first_group[self.row_argmax] == group)
        mutual = torch.zeros_like(candidate)
        for index in torch.unique(group[candidate]).tolist():
            members = torch.nonzero(candidate & (group == index)).squeeze(1)
            start = index * TILE
            recomputed = partner[self.row_argmax[members]] @ query[start : start + TILE].T  # [candidates, group rows]
            mutual[members] = _first_equal(recomputed, recomputed.amax(1)) + start == members
        return mutual


def _row_best_two(similarity: "torch.Tensor") -> tuple["torch.Tensor", "torch.Tensor", "torch.Tensor"]:
    """Each row's best value, second-best value (equal to the best on a tie) and first best
    column, of a block whose width is a multiple of `TILE`."""
    import torch

    rows = torch.arange(len(similarity), device=similarity.device)
    tiles = similarity.view(len(similarity), -1, TILE)
    tile_best = tiles.amax(2)
    best = tile_best.amax(1)
    tile = _first_equal(tile_best, best)
    within_tile = tiles[rows, tile]  # a copy: [rows, TILE]
    column = _first_equal(within_tile, best)
    within_tile[rows, column] = -torch.inf
    tile_best[rows, tile] = within_tile.amax(1)
    return best, tile_best.amax(1), tile * TILE + column


def _first_equal(values: "torch.Tensor", targets: "torch.Tensor") -> "torch.Tensor":
    """Per row, the first column of ``values`` equal to that row's target."""
    import torch

    return (values == targets[:, None]).to(torch.uint8).argmax(1)


# --------------------------------------------------------------------------------- verification


def essential_matrix(q0: np.ndarray, t0: np.ndarray, q1: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """``E = [t]x R`` of camera 1 relative to camera 0 (world-to-camera poses, q wxyz):
    ``x1^T E x0 = 0`` for normalised image coordinates of one world point."""
    r0, r1 = geometry.quaternion_to_matrix(q0), geometry.quaternion_to_matrix(q1)
    rotation = r1 @ r0.T
    translation = np.asarray(t1) - rotation @ np.asarray(t0)
    skew = np.array([[0, -translation[2], translation[1]], [translation[2], 0, -translation[0]], [-translation[1], translation[0], 0]])
    return skew @ rotation


def sampson_errors(points0: np.ndarray, points1: np.ndarray, essential: np.ndarray) -> np.ndarray:
    """Sampson distances ``[m]`` of normalised correspondences (same unit as the coordinates)."""
    x0 = np.column_stack([points0, np.ones(len(points0))])
    x1 = np.column_stack([points1, np.ones(len(points1))])
    line1 = x0 @ essential.T  # E x0
    line0 = x1 @ essential  # E^T x1
    numerator = np.einsum("ij,ij->i", x1, line1) ** 2
    denominator = line1[:, 0] ** 2 + line1[:, 1] ** 2 + line0[:, 0] ** 2 + line0[:, 1] ** 2
    return np.sqrt(numerator / np.maximum(denominator, np.finfo(float).tiny))


def epipolar_inliers(
    keypoints0: np.ndarray, keypoints1: np.ndarray, matches: np.ndarray,
    camera0: Camera, pose0: tuple[np.ndarray, np.ndarray], camera1: Camera, pose1: tuple[np.ndarray, np.ndarray],
    max_error: float,
) -> np.ndarray:
    """Boolean ``[m]``: matches within ``max_error`` pixels of the epipolar geometry of two
    known world-to-camera poses (distortion removed through the cameras' models)."""
    from locretrieval.localization.colmap_model import to_pycolmap_camera

    if not len(matches):
        return np.zeros(0, dtype=bool)
    cameras = to_pycolmap_camera(camera0), to_pycolmap_camera(camera1)
    normalised0 = cameras[0].cam_from_img(keypoints0[matches[:, 0]].astype(np.float64))
    normalised1 = cameras[1].cam_from_img(keypoints1[matches[:, 1]].astype(np.float64))
    focal = 0.5 * (cameras[0].mean_focal_length() + cameras[1].mean_focal_length())
    errors = sampson_errors(normalised0, normalised1, essential_matrix(*pose0, *pose1))
    return np.isfinite(errors) & (errors * focal <= max_error)


def two_view_inliers(
    keypoints0: np.ndarray, keypoints1: np.ndarray, matches: np.ndarray, camera0: Camera, camera1: Camera,
    settings: TwoViewSettings,
) -> np.ndarray:
    """Indices ``int32 [i]`` into ``matches`` of pycolmap's two-view geometry inliers (none
    unless the geometry is one of `GEOMETRIC_CONFIGURATIONS` with ``min_num_inliers``)."""
    import pycolmap

    from locretrieval.localization.colmap_model import to_pycolmap_camera

    if len(matches) < settings.min_num_inliers:
        return np.empty(0, dtype=np.int32)
    options = pycolmap.TwoViewGeometryOptions()
    options.min_num_inliers = settings.min_num_inliers
    options.ransac.max_error = settings.max_error
    options.ransac.random_seed = 0
    result = pycolmap.estimate_two_view_geometry(
        to_pycolmap_camera(camera0), keypoints0.astype(np.float64),
        to_pycolmap_camera(camera1), keypoints1.astype(np.float64),
        np.asarray(matches, dtype=np.uint32), options,
    )
    inliers = np.asarray(result.inlier_matches, dtype=np.int64).reshape(-1, 2)
    configuration = pycolmap.TwoViewGeometryConfiguration(int(result.config)).name  # an int in the result
    if configuration not in GEOMETRIC_CONFIGURATIONS or not len(inliers):
        return np.empty(0, dtype=np.int32)
    # map inlier keypoint pairs back to rows of `matches`
    row_of = {(int(a), int(b)): row for row, (a, b) in enumerate(matches)}
    return np.array(sorted(row_of[(int(a), int(b))] for a, b in inliers), dtype=np.int32)


# ------------------------------------------------------------------------------------ the cache


class PairMatcher:
    """Cached matches between images of ``images0`` and ``images1`` (the same set: database pairs).

    Pairs are ``(name in images0, name in images1)``. Pairs within one set are stored once in
    a canonical order and returned in the order asked. Raw and verified matches are kept in
    separate stores, so a pair verified two ways is matched once.
    """

    def __init__(
        self, images0: ImageSet, features0: FeatureStore, images1: ImageSet, features1: FeatureStore,
        settings: MatchingSettings, cache_dir: str | Path,
    ) -> None:
        self.settings = settings
        self.images = (images0, images1)
        self.features = (features0, features1)
        self.same_set = features0.folder == features1.folder
        self.index = tuple({name: i for i, name in enumerate(images.names)} for images in self.images)
        root = Path(cache_dir) / "matches" / f"{features0.folder.name}--{features1.folder.name}"
        raw_key = config_key(CACHE_VERSION, settings.ratio, settings.precision)
        poses = (images0.fingerprint(), images1.fingerprint())  # pose verification depends on them
        self.stores = {
            "none": ShardedStore(f"{root}--{raw_key}"),
            "poses": ShardedStore(f"{root}--{raw_key}--poses-{config_key(settings.max_epipolar_error, *poses)}"),
            "two_view": ShardedStore(f"{root}--{raw_key}--two-view-{config_key(dataclasses.asdict(settings.two_view))}"),
        }

    def _stored(self, pair: Pair) -> tuple[Pair, bool]:
        """The pair as stored, and whether it is the reverse of the one asked."""
        if self.same_set and pair[1] < pair[0]:
            return (pair[1], pair[0]), True
        return pair, False

    def canonical(self, pairs: Iterable[Pair]) -> list[Pair]:
        """Distinct stored forms of ``pairs`` (self-pairs dropped), sorted."""
        stored = {self._stored(pair)[0] for pair in pairs if not (self.same_set and pair[0] == pair[1])}
        for name0, name1 in stored:
            if name0 not in self.index[0] or name1 not in self.index[1]:
                raise KeyError(f"pair {(name0, name1)} is not an image pair of these sets")
        return sorted(stored)

    def ensure(self, pairs: Iterable[Pair], workers: int | None = 1, verification: str = "none") -> int:
        """Match and verify the pairs not yet cached; returns how many pairs were matched."""
        if verification not in VERIFICATIONS:
            raise ValueError(f"unknown verification {verification!r}; expected one of {VERIFICATIONS}")
        pairs = self.canonical(pairs)
        missing_raw = set(self.stores["none"].missing(map(pair_key, pairs)))
        missing_verified = set(self.stores[verification].missing(map(pair_key, pairs))) if verification != "none" else set()
        missing = missing_raw | missing_verified
        todo = [pair for pair in pairs if pair_key(pair) in missing]
        if not todo:
            return 0
        log.info("matching %d image pairs, verifying %d (%s), into %s", len(missing_raw), len(missing_verified), verification, self.stores["none"].folder)
        tasks = []
        for start in range(0, len(todo), PAIRS_PER_SHARD):
            chunk = todo[start : start + PAIRS_PER_SHARD]
            keys = {pair_key(pair) for pair in chunk}
            tasks.append((chunk, keys & missing_raw, keys & missing_verified, verification, resolve_workers(workers)))
        for _ in parallel_map(_match_shard, tasks, workers, "matching", shared=self):
            pass
        for store in self.stores.values():
            store.refresh()
        return len(missing_raw)

    def load(self, pairs: Sequence[Pair], verification: str = "none") -> dict[Pair, np.ndarray]:
        """Matches ``int32 [m, 2]`` of each pair (cached with `ensure`), in the order asked."""
        stored = {pair: self._stored(pair) for pair in pairs}
        records = self.stores[verification].read(pair_key(s) for s, _ in stored.values())
        result = {}
        for pair, (stored_pair, reversed_) in stored.items():
            matches = records[pair_key(stored_pair)]["matches"]
            result[pair] = matches[:, ::-1] if reversed_ else matches
        return result

    def verify(self, pair: Pair, matches: np.ndarray, keypoints0: np.ndarray, keypoints1: np.ndarray, verification: str) -> np.ndarray:
        """The rows of ``matches`` of ``pair`` (a stored pair) that pass ``verification``."""
        if verification == "none":
            return matches
        i, j = self.index[0][pair[0]], self.index[1][pair[1]]
        images0, images1 = self.images
        if verification == "two_view":
            return matches[two_view_inliers(keypoints0, keypoints1, matches, images0.cameras[i], images1.cameras[j], self.settings.two_view)]
        return matches[epipolar_inliers(
            keypoints0, keypoints1, matches,
            images0.cameras[i], (images0.qvec[i], images0.tvec[i]),
            images1.cameras[j], (images1.qvec[j], images1.tvec[j]),
            self.settings.max_epipolar_error,
        )]


def _match_shard(matcher: PairMatcher, task: tuple[list[Pair], set[str], set[str], str, int]) -> int:
    """Worker (one of ``workers`` sharing the matching device): raw and verified matches of a
    batch of pairs, one new shard per store."""
    pairs, missing_raw, missing_verified, verification, workers = task
    features0 = matcher.features[0].load(sorted({name0 for name0, _ in pairs}))
    features1 = matcher.features[1].load(sorted({name1 for _, name1 in pairs}))
    nearest_neighbours = matcher.settings.matcher(workers)
    matches = {key: record["matches"] for key, record in matcher.stores["none"].read(
        pair_key(pair) for pair in pairs if pair_key(pair) not in missing_raw).items()}
    to_match = [pair for pair in pairs if pair_key(pair) in missing_raw]
    for name0, group in groupby(to_match, key=lambda pair: pair[0]):
        partners = [name1 for _, name1 in group]
        computed = nearest_neighbours(features0[name0][1], [features1[name1][1] for name1 in partners])
        matches.update((pair_key((name0, name1)), pair_matches) for name1, pair_matches in zip(partners, computed))
    matcher.stores["none"].write({key: {"matches": matches[key]} for key in sorted(missing_raw)})
    matcher.stores[verification].write({
        pair_key(pair): {"matches": matcher.verify(pair, matches[pair_key(pair)], features0[pair[0]][0], features1[pair[1]][0], verification)}
        for pair in pairs if pair_key(pair) in missing_verified
    })
    return len(pairs)
