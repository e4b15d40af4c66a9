"""Mutual nearest-neighbour matching of local descriptors (`locretrieval.sfm.nearest_neighbours`): equal to
the direct computation with ties, in blocks within its memory, batched over partners, on the GPU."""

import helpers
import numpy as np
import pytest
import torch
from local_features import ternary

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.sfm import nearest_neighbours
from locretrieval.sfm.nearest_neighbours import CPU_BLOCK_BYTES, BatchedMatcher, NearestNeighbourMatcher


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
