"""`PoseCache` keeps every writer's outcomes: concurrent writers (shards of one evaluation) lose nothing."""

import multiprocessing

import numpy as np

from locretrieval.sfm import pose_cache
from locretrieval.sfm.pose_cache import PoseCache

QUERIES = [f"query/{q:03d}.jpg" for q in range(50)]
DATABASE = [f"db/{i:03d}.jpg" for i in range(64)]


def outcome(query: int, first: int):
    """A distinct outcome per entry: a pose for even queries, a failure reason for odd ones."""
    if query % 2:
        return f"reason {query}-{first}"
    return np.array([1.0, 0.0, 0.0, query / 100]), np.array([first, query, 1.5])


def assert_outcome(found, query: int, first: int) -> None:
    expected = outcome(query, first)
    if isinstance(expected, str):
        assert found == expected
    else:
        np.testing.assert_array_equal(found[0], expected[0])
        np.testing.assert_array_equal(found[1], expected[1])


def test_two_writers_that_read_before_either_saved_both_keep_their_outcomes(tmp_path):
    folder = tmp_path / "local_sfm-key"
    first, second = PoseCache(folder, QUERIES, DATABASE), PoseCache(folder, QUERIES, DATABASE)
    first.put(0, (1, 2), outcome(0, 1))
    first.put(2, (5,), outcome(2, 5))
    second.put(1, (3, 4), outcome(1, 3))
    second.put(0, (1, 2), outcome(0, 1))  # the same entry from both: stored either way, read once
    first.save()
    second.save()
    reader = PoseCache(folder, QUERIES, DATABASE)
    assert len(reader.outcomes) == 3
    assert_outcome(reader.get(2, (5,)), 2, 5)
    assert_outcome(reader.get(0, (2, 1)), 0, 1)
    assert_outcome(reader.get(1, (4, 3)), 1, 3)


def _write_many(folder, writer: int, rounds: int) -> None:
    for round_ in range(rounds):
        cache = PoseCache(folder, QUERIES, DATABASE)  # each round reads what exists, as a rerun would
        for query in range(writer, len(QUERIES), 2):
            cache.put(query, (round_, round_ + 1 + writer), outcome(query, round_))
        cache.save()


def test_concurrent_processes_saving_and_merging_lose_no_outcome(tmp_path, monkeypatch):
    folder = tmp_path / "global_sfm-key"
    rounds = 40  # past MAX_PARTS: saves merge while the other process writes
    context = multiprocessing.get_context("spawn")
    workers = [context.Process(target=_write_many, args=(folder, writer, rounds)) for writer in (0, 1)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(120)
        assert worker.exitcode == 0
    reader = PoseCache(folder, QUERIES, DATABASE)
    assert len(reader.outcomes) == rounds * len(QUERIES)
    for query in range(len(QUERIES)):
        for round_ in range(rounds):
            assert_outcome(reader.get(query, (round_, round_ + 1 + query % 2)), query, round_)
    # merging: a save after more than MAX_PARTS parts leaves one file holding everything
    monkeypatch.setattr(pose_cache, "MAX_PARTS", 4)
    assert len(list(folder.glob("*.npz"))) > 4
    merger = PoseCache(folder, QUERIES, DATABASE)
    merger.put(0, (60, 61), outcome(0, 60))
    merger.save()
    assert len(list(folder.glob("*.npz"))) == 1
    assert len(PoseCache(folder, QUERIES, DATABASE).outcomes) == rounds * len(QUERIES) + 1
