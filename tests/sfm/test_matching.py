"""Matching image pairs (`locretrieval.sfm.matching`): its device and block, matches cached per pair, the
same stored on a device as by the CPU workers."""

from pathlib import Path

import helpers
import numpy as np
import pytest
import torch
from local_features import POSES, SFM, ternary

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.config import ConfigError
from locretrieval.scene import Camera, ImageSet
from locretrieval.sfm import features as features_module
from locretrieval.sfm import matching, nearest_neighbours
from locretrieval.sfm.features import FeatureStore, extract_features
from locretrieval.sfm.matching import PairMatcher
from locretrieval.sfm.nearest_neighbours import BatchedMatcher, NearestNeighbourMatcher
from locretrieval.sfm.verification import NoVerification


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
