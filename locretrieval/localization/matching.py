"""Local feature matching between image pairs, geometric verification, and per-pair caches.

Matching is mutual nearest neighbours with Lowe's ratio test on L2-normalised descriptors,
one image against many partners at once (their descriptors stacked into one similarity block,
a float32 matrix product). Matches ``int32 [m, 2]`` hold keypoint indices (first image, second image).

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
``<cache_dir>/matches/<features 0>--<features 1>--<ratio key>/`` (raw matches, keyed by the
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

import numpy as np

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.cache import config_key
from locretrieval.config import require
from locretrieval.localization.features import FeatureStore
from locretrieval.localization.store import ShardedStore
from locretrieval.localization.workers import parallel_map
from locretrieval.scene import Camera, ImageSet

log = logging.getLogger(__name__)

VERIFICATIONS = ("none", "poses", "two_view")
#: pycolmap two-view configurations whose inliers follow a scene geometry; the others are
#: undefined, degenerate, a watermark (a fixed image overlay) or several motions.
GEOMETRIC_CONFIGURATIONS = ("CALIBRATED", "UNCALIBRATED", "PLANAR", "PANORAMIC", "PLANAR_OR_PANORAMIC")
#: Pairs per worker task (one shard of the cache).
PAIRS_PER_SHARD = 512
#: Bytes of similarity block computed at once.
SIMILARITY_BLOCK_BYTES = 1 << 27
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
    verified per ``query_verification`` (``none``: PnP RANSAC only, or ``two_view``)."""

    ratio: float
    max_epipolar_error: float
    query_verification: str
    two_view: TwoViewSettings

    def __post_init__(self) -> None:
        require(0 < self.ratio <= 1, "ratio", f"must be in (0, 1], got {self.ratio}")
        require(self.max_epipolar_error > 0, "max_epipolar_error", f"must be a positive number of pixels, got {self.max_epipolar_error}")
        require(self.query_verification in ("none", "two_view"), "query_verification",
                f"must be 'none' or 'two_view', got {self.query_verification!r}")


def pair_key(pair: Pair) -> str:
    return f"{pair[0]}\n{pair[1]}"


# ------------------------------------------------------------------------------------ matching


def normalized_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """Float32 rows of unit L2 norm (zero rows stay zero)."""
    values = np.asarray(descriptors, dtype=np.float32)
    return values / np.maximum(np.linalg.norm(values, axis=1, keepdims=True), NORM_EPSILON)


def mutual_nearest_neighbours(first: np.ndarray, others: Sequence[np.ndarray], ratio: float) -> list[np.ndarray]:
    """Matches ``int32 [m, 2]`` between descriptors ``first [n, D]`` and each of ``others``.

    A pair (i, j) is kept when j is i's nearest neighbour in that image, i is j's nearest
    neighbour, and the distance to j is at most ``ratio`` times the distance to i's second
    nearest neighbour in that image. Partners are stacked so that one matrix product gives
    a whole block of similarities, and one column-wise maximum every backward neighbour.
    """
    matches = [np.empty((0, 2), dtype=np.int32) for _ in others]
    if not len(first):
        return matches
    query = normalized_descriptors(first)
    columns = max(1, SIMILARITY_BLOCK_BYTES // (4 * len(query)))
    for block in _blocks([len(other) for other in others], columns):
        stacked = [others[index] for index in block if len(others[index])]
        if not stacked:
            continue
        similarity = query @ normalized_descriptors(np.concatenate(stacked)).T
        back = similarity.argmax(axis=0)  # each partner keypoint's nearest query keypoint
        offset = 0
        for index in block:
            size = len(others[index])
            if size:
                matches[index] = _mutual_ratio(similarity[:, offset : offset + size], back[offset : offset + size], ratio)
            offset += size
    return matches


def _blocks(sizes: Sequence[int], limit: int) -> list[range]:
    """Consecutive index ranges whose sizes add up to at most ``limit`` (or one item)."""
    blocks, start, total = [], 0, 0
    for index, size in enumerate(sizes):
        if index > start and total + size > limit:
            blocks.append(range(start, index))
            start, total = index, 0
        total += size
    if sizes:
        blocks.append(range(start, len(sizes)))
    return blocks


def _mutual_ratio(similarity: np.ndarray, back: np.ndarray, ratio: float) -> np.ndarray:
    """Mutual nearest neighbours passing the ratio test in one ``[n, m]`` similarity block
    (``back [m]``: each column's best row)."""
    rows = np.arange(len(similarity))
    nearest = similarity.argmax(axis=1)
    if similarity.shape[1] >= 2:
        best, second = np.partition(similarity, -2, axis=1)[:, [-1, -2]].T
        # squared distances of unit vectors: 2 - 2 s
        passes = np.maximum(2 - 2 * best, 0) <= ratio**2 * np.maximum(2 - 2 * second, 0)
    else:
        passes = np.ones(len(similarity), dtype=bool)
    keep = passes & (back[nearest] == rows)
    return np.stack([rows[keep], nearest[keep]], 1).astype(np.int32)


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
        raw_key = config_key(CACHE_VERSION, settings.ratio)
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
            tasks.append((chunk, keys & missing_raw, keys & missing_verified, verification))
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


def _match_shard(matcher: PairMatcher, task: tuple[list[Pair], set[str], set[str], str]) -> int:
    """Worker: raw and verified matches of a batch of pairs, one new shard per store."""
    pairs, missing_raw, missing_verified, verification = task
    features0 = matcher.features[0].load(sorted({name0 for name0, _ in pairs}))
    features1 = matcher.features[1].load(sorted({name1 for _, name1 in pairs}))
    ratio = matcher.settings.ratio
    matches = {key: record["matches"] for key, record in matcher.stores["none"].read(
        pair_key(pair) for pair in pairs if pair_key(pair) not in missing_raw).items()}
    to_match = [pair for pair in pairs if pair_key(pair) in missing_raw]
    for name0, group in groupby(to_match, key=lambda pair: pair[0]):
        partners = [name1 for _, name1 in group]
        computed = mutual_nearest_neighbours(features0[name0][1], [features1[name1][1] for name1 in partners], ratio)
        matches.update((pair_key((name0, name1)), pair_matches) for name1, pair_matches in zip(partners, computed))
    matcher.stores["none"].write({key: {"matches": matches[key]} for key in sorted(missing_raw)})
    matcher.stores[verification].write({
        pair_key(pair): {"matches": matcher.verify(pair, matches[pair_key(pair)], features0[pair[0]][0], features1[pair[1]][0], verification)}
        for pair in pairs if pair_key(pair) in missing_verified
    })
    return len(pairs)
