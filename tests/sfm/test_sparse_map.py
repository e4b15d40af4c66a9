"""A sparse map memory-mapped from its cache file: the same arrays, read only where used, and
handed to worker processes as the file's name (the global map, `locretrieval.paradigms.global_sfm`)."""

import pickle
import zipfile

import numpy as np
import pytest

from locretrieval.cache import load_arrays
from locretrieval.errors import DataFileError
from locretrieval.sfm.sparse_map import SparseMap


def a_map(images: int = 40, keypoints: int = 500, points: int = 3000) -> SparseMap:
    rng = np.random.default_rng(0)
    observations = [
        np.where(rng.random(keypoints) < 0.4, rng.integers(0, points, keypoints), -1) for _ in range(images)
    ]
    return SparseMap(rng.normal(size=(points, 3)), observations)


def test_a_memory_mapped_map_holds_the_saved_arrays_and_pickles_as_its_file_name(tmp_path):
    saved = a_map()
    saved.save(tmp_path / "map.npz")
    mapped = SparseMap.load(tmp_path / "map.npz", memory_map=True)
    assert isinstance(mapped.points, np.memmap) and all(isinstance(o, np.memmap) for o in mapped.observations)
    np.testing.assert_array_equal(mapped.points, saved.points)
    assert len(mapped.observations) == 40
    for ours, theirs in zip(mapped.observations, saved.observations):
        np.testing.assert_array_equal(ours, theirs)
    # a worker gets the file's name (some 100 bytes), not the 40 x 500 observations and 3,000 points
    sent = pickle.dumps(mapped)
    assert len(sent) < 300 < saved.points.nbytes + sum(o.nbytes for o in saved.observations) < len(pickle.dumps(saved))
    received = pickle.loads(sent)
    assert received.source == tmp_path / "map.npz"
    np.testing.assert_array_equal(received.observations[7], saved.observations[7])
    in_memory = SparseMap.load(tmp_path / "map.npz")
    assert in_memory.source is None and not isinstance(in_memory.points, np.memmap)
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(in_memory)).points, saved.points)


def test_an_empty_map_and_empty_images_are_mapped_too(tmp_path):
    empty = SparseMap(np.empty((0, 3)), [np.empty(0, dtype=np.int64), np.full(3, -1, dtype=np.int64)])
    empty.save(tmp_path / "empty.npz")
    mapped = SparseMap.load(tmp_path / "empty.npz", memory_map=True)
    assert mapped.num_points == 0 and [len(o) for o in mapped.observations] == [0, 3]


def test_a_compressed_archive_cannot_be_mapped_and_says_so(tmp_path):
    path = tmp_path / "compressed.npz"
    np.savez_compressed(path, points=np.zeros((10, 3)))
    with pytest.raises(DataFileError, match="compressed"):
        load_arrays(path, memory_map=True)
    with zipfile.ZipFile(path) as archive:
        assert archive.infolist()[0].compress_type == zipfile.ZIP_DEFLATED
    np.testing.assert_array_equal(load_arrays(path)["points"], np.zeros((10, 3)))
