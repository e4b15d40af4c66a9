"""The sharded stores of local features and matches (`locretrieval.sfm.store`)."""

import numpy as np
import pytest

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.sfm.store import ShardedStore


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
