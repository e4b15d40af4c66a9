"""Local features (pycolmap SIFT, kapture files), matching, verification and their caches."""

from dataclasses import dataclass
from pathlib import Path

import helpers
import kapture
import kapture.io.csv as kapture_csv
import kapture.io.features as kapture_features
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from scipy.spatial.transform import Rotation

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.config import ConfigError, validated
from locretrieval.scene import Camera, ImageSet, Scene
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset
from locretrieval.sfm import features as features_module
from locretrieval.sfm import matching, nearest_neighbours
from locretrieval.sfm.features import FeatureStore, LocalFeatures, extract_features
from locretrieval.sfm.inputs import SfmInputs, SfmSettings
from locretrieval.sfm.matching import PairMatcher
from locretrieval.sfm.nearest_neighbours import CPU_BLOCK_BYTES, BatchedMatcher, NearestNeighbourMatcher
from locretrieval.sfm.store import ShardedStore
from locretrieval.sfm.verification import (
    NoVerification,
    PairVerification,
    PoseVerification,
    TwoViewVerification,
    VerificationBatch,
    essential_matrices,
    sampson_errors,
    two_view_inliers,
)

SCENE = {
    "width": 256,
    "height": 192,
    "num_database": 40,
    "num_queries": 6,
    "texture_size": 128,
    "length": 20.0,
    "conditions": {"night": 0.0, "blur": 0.0, "dynamic": 0.0, "noise": 0.0},
    "database_dynamic": 0.0,
    "hard_query_fraction": 0.0,
    "workers": 1,
    "seed": 1,
}


SFM = helpers.sfm_settings()
POSES, TWO_VIEW = PoseVerification(4.0), TwoViewVerification(4.0, 15)


def features(overrides, kind="sift"):
    """The local features ``sfm/features=<kind>`` with ``overrides``."""
    return helpers.sfm_settings({"features": overrides}, choices=[f"sfm/features={kind}"]).features


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("features_scene")
    render_synthetic_dataset(helpers.render_settings(SCENE), root)
    return load_kapture_scene("tiny", [root / "mapping"], [root / "query"])


# ----------------------------------------------------------------------------------- the store


def test_sharded_store_round_trip_and_missing_keys(tmp_path, monkeypatch):
    store = ShardedStore(tmp_path / "store")
    assert store.missing(["a", "b/c", "a"]) == ["a", "b/c"]
    first = store.write(
        {
            "a": {"x": np.arange(6).reshape(3, 2), "y": np.zeros((3, 128), dtype=np.uint8)},
            "b/c": {"x": np.empty((0, 2), dtype=np.int64), "y": np.empty((0, 128), dtype=np.uint8)},
        }
    )
    second = store.write({"d\ne": {"x": np.ones((1, 2), dtype=np.int64), "y": np.ones((1, 128), dtype=np.uint8)}})
    reread = ShardedStore(tmp_path / "store")
    assert len(reread) == 3 and reread.missing(["a", "z", "d\ne"]) == ["z"]
    records = reread.read(["b/c", "a"])
    np.testing.assert_array_equal(records["a"]["x"], np.arange(6).reshape(3, 2))
    assert records["b/c"]["x"].shape == (0, 2) and records["a"]["y"].shape == (3, 128)
    assert sorted(p.name.startswith(".") for p in (tmp_path / "store").iterdir()) == [False, False]  # no temporaries
    with pytest.raises(KeyError, match="no record 'z'"):
        reread.read(["z"])
    # only the arrays asked for are read from disk
    partial = ShardedStore(tmp_path / "store")
    records = partial.read(["a", "d\ne"], arrays=("x",))
    assert [sorted(record) for record in records.values()] == [["x"], ["x"]]
    assert sorted(partial._cache) == [(first, "x"), (second, "x")]  # no "y" in memory
    np.testing.assert_array_equal(records["d\ne"]["x"], np.ones((1, 2)))
    with pytest.raises(KeyError, match="has no array 'z'"):
        partial.read(["a"], arrays=("z",))
    # over the memory budget, the least recently read arrays are dropped
    monkeypatch.setattr("locretrieval.sfm.store.CACHED_BYTES", 300)
    partial.read(["a"], arrays=("y",))
    assert list(partial._cache) == [(first, "y")] and partial._cached_bytes == 3 * 128
    (tmp_path / "store" / ".0123.h5.tmp4af.h5").write_bytes(b"half-written by another process")
    assert len(ShardedStore(tmp_path / "store")) == 3


def test_a_large_array_of_a_shard_is_read_only_for_the_records_asked_for(tmp_path, monkeypatch):
    """At 20,000 keypoints a shard's descriptors are hundreds of MB: reading them whole for one image
    would make a pair's cost grow with the shard it lies in."""
    store = ShardedStore(tmp_path / "store")
    rng = np.random.default_rng(0)
    records = {f"image{i}": {"d": rng.integers(0, 255, (10 + i, 128), dtype=np.uint8)} for i in range(8)}
    shard = store.write(records)
    monkeypatch.setattr("locretrieval.sfm.store.WHOLE_ARRAY_BYTES", 1000)  # the shard holds 10,752 bytes
    reader = ShardedStore(tmp_path / "store")
    read = reader.read(["image5", "image2", "image5"])
    assert list(read) == ["image5", "image2"]
    for name in ("image5", "image2"):
        np.testing.assert_array_equal(read[name]["d"], records[name]["d"])
    assert sorted(reader._cache[(shard, "d")]) == ["image2", "image5"] and reader._cached_bytes == (15 + 12) * 128
    np.testing.assert_array_equal(reader.read(["image7"])["image7"]["d"], records["image7"]["d"])
    assert reader._cached_bytes == (15 + 12 + 17) * 128
    monkeypatch.setattr("locretrieval.sfm.store.WHOLE_ARRAY_BYTES", 20_000)  # a small array: read whole
    whole = ShardedStore(tmp_path / "store")
    whole.read(["image0"])
    assert len(whole._cache[(shard, "d")]) == 8 and whole._cached_bytes == sum(10 + i for i in range(8)) * 128


# ------------------------------------------------------------------------------------ features


def test_sift_features_are_cached_and_in_full_resolution_pixels(scene, tmp_path):
    database = scene.database.subset(np.arange(4))
    full = extract_features(database, SFM.features, tmp_path, workers=1)
    shards = sorted(full.folder.iterdir())
    again = extract_features(database, SFM.features, tmp_path, workers=1)
    assert sorted(again.folder.iterdir()) == shards  # nothing recomputed
    half = extract_features(database, features({"max_side": 128}), tmp_path, workers=1)
    assert half.folder != full.folder
    for name in database.names:
        keypoints, descriptors = full.load([name])[name]
        assert len(keypoints) > 10 and descriptors.shape == (len(keypoints), 128) and descriptors.dtype == np.uint8
        small = half.keypoints([name])[name]
        # scaled back to the 256 x 192 image: spans it, stays inside it
        assert (
            small[:, 0].max() > 200 and (small >= 0).all() and (small[:, 0] <= 256).all() and (small[:, 1] <= 192).all()
        )
        # half-resolution keypoints land on full-resolution ones (same structures, coarser)
        distance = np.linalg.norm(small[:, None] - keypoints[None], axis=-1).min(axis=1)
        assert np.median(distance) < 1.5


def test_feature_extraction_in_worker_processes_matches_in_process(scene, tmp_path, monkeypatch):
    monkeypatch.setattr(features_module, "IMAGES_PER_SHARD", 4)  # three tasks for two workers
    database = scene.database.subset(np.arange(12))
    parallel = extract_features(database, SFM.features, tmp_path / "parallel", workers=2)
    serial = extract_features(database, SFM.features, tmp_path / "serial", workers=1)
    assert len(list(parallel.folder.glob("*.h5"))) == 3
    for name in database.names:
        for a, b in zip(parallel.load([name])[name], serial.load([name])[name]):
            np.testing.assert_array_equal(a, b)


def write_kapture_features(
    root: Path, names: list[str], keypoints: list[np.ndarray], descriptors: list[np.ndarray]
) -> None:
    """Keypoints and descriptors files as the published kapture features (e.g. R2D2) are laid out."""
    kapture_dir = str(root)
    kapture_csv.keypoints_to_file(
        kapture_csv.get_feature_csv_fullpath(kapture.Keypoints, "r2d2", kapture_dir),
        kapture.Keypoints("r2d2", np.float32, 3),
    )
    kapture_csv.descriptors_to_file(
        kapture_csv.get_feature_csv_fullpath(kapture.Descriptors, "r2d2", kapture_dir),
        kapture.Descriptors("r2d2", np.float32, 128, "r2d2", "L2"),
    )
    for name, points, values in zip(names, keypoints, descriptors):
        kapture_features.image_keypoints_to_file(
            kapture_features.get_keypoints_fullpath("r2d2", kapture_dir, name), points
        )
        kapture_features.image_descriptors_to_file(
            kapture_features.get_descriptors_fullpath("r2d2", kapture_dir, name), values
        )


def kapture_folder_with_features(root: Path, names: list[str], counts: tuple[int, ...], seed: int):
    """Two images of a kapture folder at ``root`` with ``counts`` random R2D2-style keypoints
    (x, y, scale) and descriptors: the image set, keypoints and descriptors."""
    rng = np.random.default_rng(seed)
    camera = Camera("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
    images = ImageSet(
        names, root / "sensors" / "records_data", [camera] * 2, np.tile([1.0, 0, 0, 0], (2, 1)), np.zeros((2, 3))
    )
    keypoints = [rng.uniform(0, 40, (n, 3)).astype(np.float32) for n in counts]
    descriptors = [rng.normal(size=(n, 128)).astype(np.float32) for n in counts]
    write_kapture_features(root, names, keypoints, descriptors)
    return images, keypoints, descriptors


def test_kapture_features_are_read_with_the_pixel_offset(tmp_path):
    names = ["db/a.jpg", "db/sub/b.jpg"]
    root = tmp_path / "mapping"
    images, keypoints, descriptors = kapture_folder_with_features(root, names, (7, 3), 0)
    config = {"name": "r2d2", "pixel_offset": 0.5}
    store = extract_features(images, features(config, "kapture"), tmp_path / "cache", workers=1)
    for name, points, values in zip(names, keypoints, descriptors):
        read_points, read_values = store.load([name])[name]
        np.testing.assert_allclose(read_points, points[:, :2] + 0.5)
        np.testing.assert_array_equal(read_values, values)
    (root / "reconstruction" / "descriptors" / "r2d2" / "db" / "sub" / "b.jpg.desc").unlink()
    with pytest.raises(
        FileNotFoundError, match=r"descriptors 'r2d2' of image 'db/sub/b.jpg' not found: .*b\.jpg\.desc"
    ):
        extract_features(images, features({**config, "pixel_offset": 0.0}, "kapture"), tmp_path / "cache", workers=1)
    with pytest.raises(
        ConfigError,
        match=r"sfm.features.nmae: unknown key; expected one of "
        r"\['max_keypoints', 'name', 'pixel_offset', 'score_order'\]",
    ):
        features({"nmae": "r2d2"}, "kapture")


def test_a_keypoint_budget_keeps_the_best_rows_of_kapture_features_by_their_score_order(tmp_path):
    images, keypoints, descriptors = kapture_folder_with_features(
        tmp_path / "mapping", ["db/a.jpg", "db/b.jpg"], (9, 4), 5
    )
    for order, rows in [("ascending", slice(4, 9)), ("descending", slice(0, 5))]:  # R2D2 writes the best last
        config = {"max_keypoints": 5, "name": "r2d2", "pixel_offset": 0.0, "score_order": order}
        store = extract_features(images, features(config, "kapture"), tmp_path / "cache", workers=1)
        read_points, read_values = store.load(["db/a.jpg"])["db/a.jpg"]
        np.testing.assert_array_equal(read_points, keypoints[0][rows, :2])
        np.testing.assert_array_equal(read_values, descriptors[0][rows])
        assert len(store.keypoints(["db/b.jpg"])["db/b.jpg"]) == 4  # fewer than the budget: all
    with pytest.raises(
        ConfigError, match=r"sfm.features.max_keypoints: needs the score order of the kapture features 'r2d2'"
    ):
        features({"max_keypoints": 5, "score_order": None}, "kapture")


def test_a_keypoint_budget_keeps_pycolmaps_strongest_sift_detections(scene, tmp_path):
    database = scene.database.subset(np.arange(3))
    full = extract_features(database, SFM.features, tmp_path, workers=1)
    budget = extract_features(database, features({"max_keypoints": 12}), tmp_path, workers=1)
    assert budget.folder != full.folder
    for name in database.names:
        all_points, kept = full.keypoints([name])[name], budget.keypoints([name])[name]
        assert len(all_points) > 20 and len(kept) == 12
        assert len(np.unique(kept, axis=0)) >= 10  # extra orientations of a detection come last
        # the budget's keypoints are among the full set's (the same detector, its strongest detections)
        assert np.linalg.norm(kept[:, None] - all_points[None], axis=-1).min(axis=1).max() < 1e-3


def test_sift_budget_prefers_new_locations_to_extra_orientations():
    points = np.array([[1, 1], [1, 1], [2, 2], [3, 3], [3, 3], [4, 4]], dtype=np.float32)  # pycolmap's order

    def sift(budget):
        return features_module.SiftFeatures(budget, 1600, 0, 8192, 0.004)

    np.testing.assert_array_equal(sift(4).best_rows(points), [0, 2, 3, 5])
    np.testing.assert_array_equal(sift(5).best_rows(points), [0, 1, 2, 3, 5])
    np.testing.assert_array_equal(sift(None).best_rows(points), np.arange(6))


@pytest.mark.parametrize(("order", "expected"), [("ascending", [3, 4, 5]), ("descending", [0, 1, 2])])
def test_kapture_budget_keeps_the_best_scored_rows_of_the_files_order(order, expected):
    features = features_module.KaptureFeatures(3, "r2d2", 0.5, order)
    np.testing.assert_array_equal(features.best_rows(np.zeros((6, 2), np.float32)), expected)
    np.testing.assert_array_equal(features.best_rows(np.zeros((3, 2), np.float32)), [0, 1, 2])


# ------------------------------------------------------------------------------------ matching


def reference_matches(first: np.ndarray, second: np.ndarray, ratio: float) -> set[tuple[int, int]]:
    """Mutual nearest neighbours with the ratio test, by explicit distances (float64)."""
    a = first / np.linalg.norm(first, axis=1, keepdims=True)
    b = second / np.linalg.norm(second, axis=1, keepdims=True)
    distances = np.linalg.norm(a[:, None] - b[None], axis=-1)
    result = set()
    for i, row in enumerate(distances):
        order = np.argsort(row)
        j = order[0]
        if row[j] <= ratio * row[order[1]] and np.argmin(distances[:, j]) == i:
            result.add((i, int(j)))
    return result


def direct_matches(first: np.ndarray, second: np.ndarray, ratio: float) -> np.ndarray:
    """The whole float64 similarity matrix, argmax both ways (first index on ties), the ratio
    test on each row's two best values (equal on a tie; no test with a single column)."""
    a = first / np.linalg.norm(first, axis=1, keepdims=True)
    b = second / np.linalg.norm(second, axis=1, keepdims=True)
    similarity = a @ b.T
    nearest, back = similarity.argmax(1), similarity.argmax(0)
    two_best = np.sort(np.column_stack([similarity, np.full(len(a), -1.0)]), axis=1)[
        :, -2:
    ]  # -1: a lone column's runner-up
    passes = (
        2 - 2 * two_best[:, 1] <= ratio**2 * (2 - 2 * two_best[:, 0])
        if similarity.shape[1] >= 2
        else np.ones(len(a), bool)
    )
    keep = passes & (back[nearest] == np.arange(len(a)))
    return np.column_stack([np.flatnonzero(keep), nearest[keep]])


def ternary(count: int, dimension: int, nonzero: int, rng: np.random.Generator) -> np.ndarray:
    """Rows of ``nonzero`` entries +-1 (a power of 4, so that normalised rows hold powers of two
    and every similarity is exact in float16, float32 and float64): many exact ties."""
    rows = np.zeros((count, dimension))
    for row in rows:
        row[rng.choice(dimension, nonzero, replace=False)] = rng.choice([-1.0, 1.0], nonzero)
    return rows


# blocks: one; 128 x 128 (several row blocks and column tiles, padded tiles)
@pytest.mark.parametrize("block_bytes", [nearest_neighbours.CPU_BLOCK_BYTES, 4 * 128 * 128])
@pytest.mark.parametrize("precision", ["float32", "float16"])
def test_matcher_equals_the_direct_computation_with_ties(block_bytes, precision):
    rng = np.random.default_rng(3)
    for rows, columns, dimension, nonzero in [(300, 500, 32, 4), (260, 131, 16, 4), (129, 257, 64, 16), (7, 1, 16, 4)]:
        first, second = ternary(rows, dimension, nonzero, rng), ternary(columns, dimension, nonzero, rng)
        first[5], second[-1] = second[0], first[0]  # exact matches between the sets
        for ratio in (1.0, 0.9, 0.7):
            matcher = NearestNeighbourMatcher(ratio, precision, block_bytes)
            expected = direct_matches(first, second, ratio)
            np.testing.assert_array_equal(
                matcher(first, [second])[0], expected, err_msg=f"{rows}x{columns}, ratio {ratio}"
            )


def test_matcher_equals_an_explicit_computation_on_real_valued_descriptors():
    rng = np.random.default_rng(1)
    first = rng.normal(size=(60, 16))
    # partners: noisy copies of a shuffled part of `first`, plus distractors; one empty
    others = []
    for size in (40, 75, 0, 1):
        rows = rng.permutation(60)[: min(size, 30)]
        others.append(
            np.concatenate(
                [first[rows] + 0.3 * rng.normal(size=(len(rows), 16)), rng.normal(size=(size - len(rows), 16))]
            )
        )
    matches = NearestNeighbourMatcher(0.8, "float32", 4 * 128 * 128)(first, others)
    for other, found in zip(others, matches):
        assert found.dtype == np.int32 and found.shape[1] == 2
        if len(other) >= 2:
            assert {tuple(m) for m in found.tolist()} == reference_matches(first, other, 0.8)
    assert len(matches[0]) > 10 and len(matches[2]) == 0
    assert len(matches[3]) <= 1  # a single partner descriptor: no ratio test, mutual check only


def test_matcher_block_shape_bounds_the_similarity_memory():
    matcher = NearestNeighbourMatcher(0.8, "float32", 8 << 20)
    # about square, equal blocks: 20,000 columns = 157 tiles of 128 in 15 blocks of 11 tiles; rows in 15 blocks of 1,408
    assert matcher.block_shape(20_000, 20_000, 4) == (1408, 1408)
    assert matcher.block_shape(20_000, 300, 4) == (
        5120,
        384,
    )  # at most 5,376 rows fit: 4 blocks of 5,000 rounded up to 128
    assert matcher.block_shape(2_000, 2_000, 4) == (2000, 1024)  # 2 x 8 tiles; 2,048 rows fit
    assert matcher.block_shape(50, 20_000, 2) == (50, 2048)  # float16: 16 tiles (a side of 2,048) in 10 blocks of 16
    for rows, columns, size in [(20_000, 20_000, 4), (3, 5, 4), (20_000, 300, 2), (1_000, 70_000, 4), (129, 64, 4)]:
        height, width = matcher.block_shape(rows, columns, size)
        assert (
            height * width * size <= 8 << 20
            and width % nearest_neighbours.TILE == 0
            and (height == rows or height % nearest_neighbours.TILE == 0)
        )


PARTNER_SIZES = (500, 131, 1, 0, 257, 300)


def ternary_partners(
    rng: np.random.Generator, rows: int = 260, dimension: int = 32
) -> tuple[np.ndarray, list[np.ndarray]]:
    """A first image and partners of several sizes (one of one row, one empty) with exact ties
    and exact matches between them."""
    first = ternary(rows, dimension, 4, rng)
    partners = [ternary(size, dimension, 4, rng) for size in PARTNER_SIZES]
    first[5], partners[0][-1], partners[4][3] = partners[0][0], first[0], first[7]
    return first, partners


# batches: every partner at once; a few partners per batch, the first image's rows split in blocks of 128
@pytest.mark.parametrize("batch_bytes", [1 << 30, 4 * 128 * 600])
@pytest.mark.parametrize("precision", ["float32", "float16"])
def test_batched_matcher_equals_the_direct_computation_and_the_blocked_matcher_with_ties(batch_bytes, precision):
    first, partners = ternary_partners(np.random.default_rng(5))
    counts = {}
    for ratio in (1.0, 0.9, 0.7):
        batched = BatchedMatcher(ratio, "cpu", precision, batch_bytes)(first, partners)
        counts[ratio] = [len(found) for found in batched]
        blocked = NearestNeighbourMatcher(ratio, precision, 4 * 128 * 128)(first, partners)
        for size, found, expected in zip(PARTNER_SIZES, batched, blocked):
            assert found.dtype == np.int32 and found.shape[1] == 2
            np.testing.assert_array_equal(found, expected, err_msg=f"{size} partner rows, ratio {ratio}")
            if size:
                np.testing.assert_array_equal(found, direct_matches(first, partners[PARTNER_SIZES.index(size)], ratio))
    assert counts[1.0][0] > 20 and counts[0.7][0] >= 2 and counts[1.0][3] == 0  # the exact copies pass any ratio


def test_batched_matcher_splits_its_work_within_the_memory_it_is_given():
    widths = [500, 131, 1, 257, 300]  # padded to 512, 256, 128, 384, 384
    # 800 columns of 260 float32 rows: 512 + 512 do not fit, 2 x 256 do, 3 x 384 do not, 2 x 384 do
    assert BatchedMatcher(0.8, "cpu", "float32", 4 * 260 * 800)._batches(260, widths, 4) == [[0], [1, 2], [3, 4]]
    assert BatchedMatcher(0.8, "cpu", "float32", 1 << 30)._batches(260, widths, 4) == [[0, 1, 2, 3, 4]]
    # 295 columns: each partner alone, the 512-wide one in row blocks of 128 (the smallest block)
    assert BatchedMatcher(0.8, "cpu", "float32", 4 * 128 * 600)._batches(260, widths, 4) == [[0], [1], [2], [3], [4]]


def test_batched_matcher_equals_an_explicit_computation_on_real_valued_descriptors():
    rng = np.random.default_rng(1)
    first = rng.normal(size=(60, 16))
    others = [
        np.concatenate([first[rng.permutation(60)[:30]] + 0.3 * rng.normal(size=(30, 16)), rng.normal(size=(size, 16))])
        for size in (10, 45, 200)
    ]
    for other, found in zip(others, BatchedMatcher(0.8, "cpu", "float32", 4 * 128 * 300)(first, others)):
        assert len(found) > 10 and {tuple(m) for m in found.tolist()} == reference_matches(first, other, 0.8)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (none here)")
@pytest.mark.parametrize("batch_mib", [None, 0.3])
@pytest.mark.parametrize("precision", ["float32", "float16"])
def test_batched_matcher_on_the_gpu_equals_the_cpu_with_ties(precision, batch_mib):
    rng = np.random.default_rng(4)
    first, partners = ternary_partners(rng, rows=3000, dimension=64)
    partners += [ternary(2500, 64, 16, rng), ternary(20_000, 64, 16, rng)]
    settings = helpers.sfm_settings(
        {"matching": {"device": "cuda", "precision": precision, "block_mib": batch_mib}}
    ).matching
    gpu = settings.matcher()
    assert isinstance(gpu, BatchedMatcher) and gpu.device.startswith("cuda")
    for found, expected in zip(
        gpu(first, partners), NearestNeighbourMatcher(0.8, precision, CPU_BLOCK_BYTES)(first, partners)
    ):
        np.testing.assert_array_equal(found, expected)


def test_matching_settings_resolve_the_device_and_the_block():
    settings = helpers.sfm_settings({"matching": {"block_mib": 2.5, "precision": "float16"}}).matching
    matcher = settings.matcher()
    assert (matcher.device, matcher.precision, matcher.block_bytes, matcher.ratio) == (
        "cpu",
        "float16",
        int(2.5 * 2**20),
        0.8,
    )
    assert helpers.sfm_settings().matching.matcher().block_bytes == nearest_neighbours.CPU_BLOCK_BYTES
    # where and in which blocks matches are computed is not what determines them
    assert (
        "device" not in settings.identity()
        and "block_mib" not in settings.identity()
        and settings.identity()["precision"] == "float16"
    )
    with pytest.raises(ConfigError, match="sfm.matching.precision"):
        helpers.sfm_settings({"matching": {"precision": "int8"}})


def geometric_error(x0: np.ndarray, x1: np.ndarray, q0, t0, q1, t1) -> float:
    """The gold-standard error: distance to the closest pair of exact projections of one
    3D point (optimal triangulation by least squares), in normalised coordinates."""
    from scipy.optimize import least_squares

    R0, R1 = geometry.quaternion_to_matrix(q0), geometry.quaternion_to_matrix(q1)

    def residuals(point):
        a, b = R0 @ point + t0, R1 @ point + t1
        return np.concatenate([a[:2] / a[2] - x0, b[:2] / b[2] - x1])

    start = np.linalg.solve(R0, np.append(x0, 1.0) * 6.0 - t0)
    return float(np.linalg.norm(least_squares(residuals, start, xtol=1e-15, ftol=1e-15).fun))


def test_sampson_error_approximates_the_geometric_error_and_bounds_matches_in_pixels():
    rng = np.random.default_rng(2)
    q0, q1 = (np.roll(Rotation.from_rotvec(rng.normal(0, 0.1, 3)).as_quat(), 1) for _ in range(2))
    t0, t1 = np.zeros(3), np.array([1.0, 0.1, 0.0])
    points = rng.uniform([-2, -2, 4], [2, 2, 8], (50, 3))
    cam0 = points @ geometry.quaternion_to_matrix(q0).T + t0
    cam1 = points @ geometry.quaternion_to_matrix(q1).T + t1
    x0, x1 = cam0[:, :2] / cam0[:, 2:], cam1[:, :2] / cam1[:, 2:]
    essential = essential_matrices(q0, t0, q1, t1)
    assert sampson_errors(x0, x1, essential).max() < 1e-10
    noisy = x1 + rng.normal(0, 0.004, x1.shape)
    expected = [geometric_error(a, b, q0, t0, q1, t1) for a, b in zip(x0[:10], noisy[:10])]
    np.testing.assert_allclose(sampson_errors(x0[:10], noisy[:10], essential), expected, rtol=0.02)
    # in pixels (f = 500): 25 exact matches, 25 moved 10 px off their epipolar line
    camera = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
    line = np.column_stack([x0, np.ones(50)]) @ essential.T
    normal = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    moved = np.where((np.arange(50) < 25)[:, None], x1, x1 + 0.02 * normal)
    matches = np.column_stack([np.arange(50), np.arange(50)])
    images = ImageSet(["a.jpg", "b.jpg"], Path("/nonexistent"), [camera] * 2, np.stack([q0, q1]), np.stack([t0, t1]))
    keypoints = {"a.jpg": x0 * 500 + [320, 240], "b.jpg": moved * 500 + [320, 240]}
    (kept,) = PoseVerification(2.0).verify(VerificationBatch(images, images, [(0, 1)], [matches], keypoints, keypoints))
    np.testing.assert_array_equal(kept, matches[:25])


def test_matches_are_cached_per_pair_and_reused_for_larger_sets(scene, tmp_path, monkeypatch):
    database = scene.database
    store = extract_features(database, SFM.features, tmp_path, workers=1)
    matcher = PairMatcher(database, store, database, store, SFM.matching, tmp_path)
    calls = []
    real = NearestNeighbourMatcher.__call__
    monkeypatch.setattr(
        NearestNeighbourMatcher,
        "__call__",
        lambda self, first, others: calls.append(len(others)) or real(self, first, others),
    )
    names = database.names
    # same heading at neighbouring stations (8 cameras per station)
    small = [(names[0], names[8]), (names[9], names[1]), (names[8], names[16])]
    assert matcher.ensure(small, workers=1, verification=NoVerification()) == 3
    assert sum(calls) == 3
    # verifying cached raw matches matches nothing again
    assert matcher.ensure(small, workers=1, verification=POSES) == 0
    assert sum(calls) == 3
    raw_small, verified_small = matcher.load(small, NoVerification()), matcher.load(small, POSES)
    for pair in small:
        assert {tuple(m) for m in verified_small[pair].tolist()} <= {tuple(m) for m in raw_small[pair].tolist()}
    assert sum(map(len, verified_small.values())) > 0
    # the same pairs, reversed or repeated, are not matched again; a larger set matches only its new pairs
    assert (
        matcher.ensure(
            [(names[8], names[0]), (names[1], names[9]), (names[0], names[0])], workers=1, verification=POSES
        )
        == 0
    )
    larger = small + [(names[0], names[16]), (names[17], names[1])]
    assert matcher.ensure(larger, workers=1, verification=POSES) == 2
    assert sum(calls) == 5
    forward = matcher.load([(names[1], names[9])], POSES)[(names[1], names[9])]
    backward = matcher.load([(names[9], names[1])], POSES)[(names[9], names[1])]
    np.testing.assert_array_equal(backward, forward[:, ::-1])
    # verification keeps a subset of the raw matches, and a new matcher reads the cache
    raw = PairMatcher(database, store, database, store, SFM.matching, tmp_path).load(
        [(names[1], names[9])], NoVerification()
    )[(names[1], names[9])]
    assert len(forward) and {tuple(m) for m in forward.tolist()} <= {tuple(m) for m in raw.tolist()}
    with pytest.raises(KeyError, match="no record"):
        matcher.load([(names[5], names[6])], NoVerification())


def test_pose_verification_keeps_the_true_matches_by_the_rendered_depth(scene, tmp_path):
    """A raw match is true when the depth of the first image maps its keypoint onto the
    second; verification against the known poses keeps every true match and rejects only
    wrong ones (wrong matches along the epipolar line, e.g. on repeated floor tiles, remain)."""
    import kapture.io.records as kapture_records

    database = scene.database
    store = extract_features(database, SFM.features, tmp_path, workers=1)
    matcher = PairMatcher(database, store, database, store, SFM.matching, tmp_path)
    first, second = 1, 9  # looking across the corridor from neighbouring stations
    pair = (database.names[first], database.names[second])
    matcher.ensure([pair], workers=1, verification=POSES)
    raw = matcher.load([pair], NoVerification())[pair]
    verified = {tuple(m) for m in matcher.load([pair], POSES)[pair].tolist()}
    keypoints = store.keypoints(list(pair))
    camera = database.cameras[first]
    depth = kapture_records.depth_map_from_file(str(database.depth_paths[first]), (camera.width, camera.height))
    pixels = keypoints[pair[0]][raw[:, 0]]
    z = depth[pixels[:, 1].astype(int), pixels[:, 0].astype(int)]
    rays = np.column_stack([pixels, np.ones(len(pixels))]) @ np.linalg.inv(camera.calibration_matrix()).T
    R0, R1 = (geometry.quaternion_to_matrix(database.qvec[i]) for i in (first, second))
    world = (rays * z[:, None] - database.tvec[first]) @ R0
    projected = (world @ R1.T + database.tvec[second]) @ database.cameras[second].calibration_matrix().T
    error = np.linalg.norm(projected[:, :2] / projected[:, 2:] - keypoints[pair[1]][raw[:, 1]], axis=1)
    kept = np.array([tuple(m) in verified for m in raw.tolist()])
    true = error < 1.0
    assert true.sum() >= 15
    assert kept[true].all()
    assert (~kept).any() and (error[~kept] > 4.0).all()


def test_two_view_verification_keeps_raw_matches_consistent_with_the_poses(scene, tmp_path):
    database = scene.database
    store = extract_features(database, SFM.features, tmp_path, workers=1)
    matcher = PairMatcher(database, store, database, store, SFM.matching, tmp_path)
    first, second = 1, 9
    pair = (database.names[first], database.names[second])
    matcher.ensure([pair], workers=1, verification=TWO_VIEW)
    raw, verified = matcher.load([pair], NoVerification())[pair], matcher.load([pair], TWO_VIEW)[pair]
    assert len(verified) >= 15 and {tuple(m) for m in verified.tolist()} <= {tuple(m) for m in raw.tolist()}
    keypoints = store.keypoints(list(pair))
    batch = VerificationBatch(database, database, [(first, second)], [verified], keypoints, keypoints)
    (consistent,) = PoseVerification(4.0).verify(batch)
    assert len(consistent) > 0.9 * len(verified)


@pytest.mark.parametrize(
    "configuration, kept",
    [
        ("CALIBRATED", True),
        ("PLANAR_OR_PANORAMIC", True),
        ("WATERMARK", False),
        ("MULTIPLE", False),
        ("DEGENERATE", False),
    ],
)
def test_two_view_inliers_only_of_scene_geometries(configuration, kept, monkeypatch):
    import pycolmap

    class Result:
        config = int(getattr(pycolmap.TwoViewGeometryConfiguration, configuration))  # as pycolmap returns it
        inlier_matches = np.array([[3, 1], [0, 2]])

    monkeypatch.setattr(pycolmap, "estimate_two_view_geometry", lambda *args: Result())
    camera = Camera("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
    keypoints = np.zeros((10, 2))
    matches = np.array([[3, 1], [0, 2]] + [[i, i] for i in range(4, 10)])
    inliers = two_view_inliers(
        keypoints, keypoints, matches, camera, camera, TwoViewVerification(max_error=4.0, min_num_inliers=5)
    )
    np.testing.assert_array_equal(inliers, [0, 1] if kept else [])


def ternary_feature_scene(cache: Path, count: int = 12, keypoints: int = 300) -> tuple[ImageSet, "FeatureStore"]:
    """``count`` posed images of one camera whose cached features are ternary descriptors (exact
    similarities: the CPU and batched matchers agree bit for bit) at random keypoints."""
    rng = np.random.default_rng(9)
    camera = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
    qvec = geometry.normalize_quaternions(np.column_stack([np.ones(count), 0.05 * rng.normal(size=(count, 3))]))
    images = ImageSet(
        [f"db/{i:02d}.jpg" for i in range(count)],
        Path("/nonexistent"),
        [camera] * count,
        qvec,
        rng.normal(size=(count, 3)),
    )
    store = features_module.feature_store(images, SFM.features, cache)
    shared = ternary(keypoints // 2, 32, 4, rng)  # rows every image holds: mutual matches across pairs
    store.store.write(
        {
            name: {
                "keypoints": rng.uniform(0, 480, (keypoints, 2)).astype(np.float32),
                "descriptors": np.concatenate([shared, ternary(keypoints - len(shared), 32, 4, rng)])[
                    rng.permutation(keypoints)
                ],
            }
            for name in images.names
        }
    )
    return images, store


def stored(matcher: PairMatcher, pairs, verification) -> dict:
    return {pair: matches.tolist() for pair, matches in matcher.load(pairs, verification).items()}


@pytest.mark.parametrize("workers", [1, 2])
def test_matching_on_a_device_stores_what_the_cpu_workers_store(tmp_path, monkeypatch, workers):
    """The device path (one owner process, descriptors read ahead and kept resident, each image
    against its partners in one product, shards verified and written by CPU workers) run with the
    batched matcher on the CPU, with room for 3 images' descriptors: the same stores as the CPU path."""
    images, store = ternary_feature_scene(tmp_path / "cpu")
    pairs = [(a, b) for a in images.names for b in images.names if a < b]
    on_cpu = PairMatcher(images, store, images, store, SFM.matching, tmp_path / "cpu")
    assert on_cpu.ensure(pairs, 1, POSES) == len(pairs)

    images, store = ternary_feature_scene(tmp_path / "device")
    on_device = PairMatcher(images, store, images, store, SFM.matching, tmp_path / "device")
    monkeypatch.setattr(matching, "PAIRS_PER_SHARD", 5)  # 14 shards: the worker pool verifies them
    monkeypatch.setattr(matching, "HOST_RESIDENT_BYTES", 3 * 300 * 32 * 4)
    batched = BatchedMatcher(SFM.matching.ratio, "cpu", SFM.matching.precision, 4 * 300 * 1024)
    monkeypatch.setattr(matching.MatchingSettings, "matcher", lambda self: batched)
    reads = []
    real = matching.partial_descriptors
    monkeypatch.setattr(
        matching,
        "partial_descriptors",
        lambda features: lambda names: reads.append(len(names)) or real(features)(names),
    )
    assert on_device.ensure(pairs, workers, POSES) == len(pairs)
    assert stored(on_device, pairs, NoVerification()) == stored(on_cpu, pairs, NoVerification())
    assert stored(on_device, pairs, POSES) == stored(on_cpu, pairs, POSES)
    assert sum(map(len, stored(on_device, pairs, NoVerification()).values())) > len(pairs) * 100
    assert (
        0
        < sum(map(len, stored(on_device, pairs, POSES).values()))
        < sum(map(len, stored(on_device, pairs, NoVerification()).values()))
    )
    # evicted images are read again, but no image twice for one shard
    assert len(images) < sum(reads) <= len(pairs) * 2


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (none here)")
@pytest.mark.parametrize("precision", ["float32", "float16"])
def test_matching_on_the_gpu_stores_what_the_cpu_workers_store(tmp_path, monkeypatch, precision):
    """The GPU owner process (resident descriptors, batched products, CPU workers verifying and
    writing) against the CPU workers, through `PairMatcher.ensure`, at both precisions."""
    cpu = helpers.sfm_settings({"matching": {"precision": precision}}).matching
    gpu = helpers.sfm_settings({"matching": {"device": "cuda", "precision": precision}}).matching
    assert isinstance(gpu.matcher(), BatchedMatcher)
    monkeypatch.setattr(matching, "PAIRS_PER_SHARD", 5)
    found = []
    for name, settings in (("cpu", cpu), ("gpu", gpu)):
        images, store = ternary_feature_scene(tmp_path / name)
        pairs = [(a, b) for a in images.names for b in images.names if a < b]
        matcher = PairMatcher(images, store, images, store, settings, tmp_path / name)
        assert matcher.ensure(pairs, 2, POSES) == len(pairs)
        found.append((stored(matcher, pairs, NoVerification()), stored(matcher, pairs, POSES)))
    assert found[0] == found[1]


@dataclass
class GridFeatures(LocalFeatures):
    """A kind of local features from outside the package: keypoints on a grid of ``step`` px,
    each a descriptor of its grid cell (so images of one camera match cell for cell)."""

    max_keypoints: int | None
    step: int

    def identity(self) -> dict:
        return {"type": "grid", "step": self.step, "max_keypoints": self.max_keypoints}

    def records(self):
        def record(name: str, path: Path) -> dict[str, np.ndarray]:
            xy = np.stack(np.meshgrid(np.arange(8, 200, self.step), np.arange(8, 150, self.step)), -1).reshape(-1, 2)
            cells = np.random.default_rng(0).normal(size=(len(xy), 16)).astype(np.float32)
            return {"keypoints": xy.astype(np.float32), "descriptors": cells}

        return record

    def _best_rows(self, keypoints: np.ndarray, budget: int) -> np.ndarray:
        return np.arange(budget)  # the grid's first cells


def test_local_features_and_a_verification_from_outside_the_package_are_chosen_by_target(tmp_path, monkeypatch):
    nodes = {
        "features": {"_target_": f"{__name__}.GridFeatures", "max_keypoints": 50, "step": 16},
        "query_verification": {
            "_target_": "locretrieval.sfm.verification.PoseVerification",
            "max_epipolar_error": 2.0,
        },
    }
    plain = OmegaConf.to_container(helpers.compose_config("evaluate").sfm, resolve=True)
    settings = validated(
        SfmSettings, {**plain, **nodes, "workers": 1, "matching": {**plain["matching"], "device": "cpu"}}, "sfm"
    )
    assert isinstance(settings.features, GridFeatures) and settings.query_verification == PoseVerification(2.0)
    camera = Camera("PINHOLE", 200, 150, (150.0, 150.0, 100.0, 75.0))
    images = ImageSet(
        ["a.jpg", "b.jpg"], Path("/nonexistent"), [camera] * 2, np.tile([1.0, 0, 0, 0], (2, 1)), np.zeros((2, 3))
    )
    store = extract_features(images, settings.features, tmp_path, workers=1)
    assert len(store.keypoints(["a.jpg"])["a.jpg"]) == 50  # its budget, its keypoint order
    matcher = PairMatcher(images, store, images, store, settings.matching, tmp_path)
    matcher.ensure([("a.jpg", "b.jpg")], 1, settings.query_verification)
    np.testing.assert_array_equal(
        matcher.load([("a.jpg", "b.jpg")], settings.query_verification)[("a.jpg", "b.jpg")],
        np.tile(np.arange(50), (2, 1)).T,
    )
    wrong = {**plain, "features": {"_target_": "locretrieval.sfm.verification.NoVerification"}}
    with pytest.raises(
        ConfigError,
        match=r"sfm.features._target_: locretrieval.sfm.verification.NoVerification "
        r"is not a part of sfm.features: a part there is a LocalFeatures",
    ):
        validated(SfmSettings, wrong, "sfm")
    with pytest.raises(ConfigError, match=r"sfm.query_verification.max_eror: unknown key"):
        validated(SfmSettings, {**plain, "query_verification": {**nodes["query_verification"], "max_eror": 1}}, "sfm")


@dataclass(unsafe_hash=True)
class FirstMatches(PairVerification):
    """A database verification from outside the package: each pair's first ``count`` matches."""

    count: int

    def store_name(self, images0, images1):
        return f"first-{self.count}"

    def verify(self, batch):
        return [matches[: self.count] for matches in batch.matches]


def test_a_database_verification_from_outside_the_package_is_chosen_through_the_config(tmp_path, monkeypatch):
    settings = helpers.sfm_settings(
        choices=[
            "~sfm.features",
            f"+sfm.features={{_target_: {__name__}.GridFeatures, max_keypoints: 50, step: 16}}",
            "~sfm.database_verification",
            f"+sfm.database_verification={{_target_: {__name__}.FirstMatches, count: 3}}",
        ]
    )
    assert settings.database_verification == FirstMatches(3)
    camera = Camera("PINHOLE", 200, 150, (150.0, 150.0, 100.0, 75.0))
    images = ImageSet(
        ["a.jpg", "b.jpg"], Path("/nonexistent"), [camera] * 2, np.tile([1.0, 0, 0, 0], (2, 1)), np.zeros((2, 3))
    )
    inputs = SfmInputs.prepare(Scene("grid", images, images.subset(np.arange(0))), settings, tmp_path)
    pair = ("a.jpg", "b.jpg")
    inputs.database_pairs.ensure([pair], 1, inputs.database_verification)
    np.testing.assert_array_equal(
        inputs.database_pairs.load([pair], inputs.database_verification)[pair], np.tile(np.arange(3), (2, 1)).T
    )
    default = helpers.sfm_settings().database_verification
    assert default == PoseVerification(
        OmegaConf.load(helpers.CONFIGS / "sfm/database_verification/poses.yaml").max_epipolar_error
    )


@pytest.mark.parametrize("level, shown", [(None, False), ("0", True)])
def test_pycolmap_logs_below_warnings_only_when_glog_is_asked_to(level, shown):
    """The project's processes set glog's default level to warnings (``GLOG_minloglevel=2``): no
    ``Creating SIFT CPU feature extractor`` line per extractor, unless the environment asks."""
    import os
    import subprocess
    import sys

    environment = {key: value for key, value in os.environ.items() if key != "GLOG_minloglevel"}
    if level is not None:
        environment["GLOG_minloglevel"] = level
    script = "import locretrieval, pycolmap\npycolmap.FeatureExtractor.create(pycolmap.FeatureExtractionOptions())"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=environment, timeout=120)
    assert done.returncode == 0, done.stderr
    assert ("Creating SIFT CPU feature extractor" in done.stderr) == shown
