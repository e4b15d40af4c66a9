"""`PoseCache` keeps every writer's outcomes: concurrent writers (shards of one evaluation) lose nothing,
and a run killed (SIGKILL) in the middle of a paradigm loses no finished registration: the rerun
registers only what had not been saved, and its tables equal an uninterrupted run's."""

import gzip
import multiprocessing
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from locretrieval.cache import load_arrays
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


ROOT = Path(__file__).resolve().parents[2]


#: Enough registrations (64 queries x 3 rankings x k = 5, 10, 15, 20) for local SfM's register stage,
#: which reads maps triangulated before it, to run several save intervals (`SAVE_SECONDS`). 100
#: bootstrap resamples and a vocabulary from 20,000 RootSIFTs in 10 iterations: the tables of each
#: of the three runs at a fraction of the default's work.
COMMAND = [
    "data.render.width=160",
    "data.render.height=120",
    "data.render.num_database=30",
    "data.render.num_queries=64",
    "data.render.texture_size=64",
    "data.render.length=24.0",
    "data.render.seed=3",
    "model.max_side=160",
    "model.step=4",
    "model.vocabulary_samples=20000",
    "model.kmeans_iterations=10",
    "metrics.uncertainty.resamples=100",
    "subsets.blur_width=160",
    "groundtruth.enabled=[relative_pose]",
    "paradigms.global_sfm.enabled=false",
    "paradigms.local_sfm.k=[5,10,15,20]",
    "output.ltvl=false",
    "report.figure_formats=[]",
    "report.scene_view.enabled=false",
]


TABLES = ("results.csv", "query_errors.csv.gz", "estimated_poses.csv.gz")


def evaluate(root: Path, run: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, str(ROOT / "evaluate.py"), f"paths.root_dir={root}", f"hydra.run.dir={root / run}", *COMMAND],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # its worker processes are killed with it
    )


def finished(process: subprocess.Popen) -> str:
    output, _ = process.communicate(timeout=900)
    assert process.returncode == 0, output[-3000:]
    return output


def saved_outcomes(root: Path) -> int:
    """Registration outcomes on disk: the distinct keys of every part of the local-SfM pose cache."""
    parts = list((root / ".cache" / "poses").glob("local_sfm-*/[!.]*.npz"))
    return len({key.tobytes() for part in parts for key in load_arrays(part)["keys"]})


def table(path: Path) -> bytes:
    return gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()


@pytest.mark.slow
def test_a_run_killed_mid_paradigm_loses_no_saved_registration(tmp_path):
    killed = evaluate(tmp_path, "killed")
    while not list((tmp_path / ".cache" / "poses").glob("local_sfm-*/[!.]*.npz")):
        assert killed.poll() is None, killed.communicate()[0][-3000:]
        time.sleep(0.05)
    os.killpg(killed.pid, signal.SIGKILL)
    killed.communicate()
    before = saved_outcomes(tmp_path)
    assert before > 0

    rerun = finished(evaluate(tmp_path, "rerun"))
    registered = sum(int(n) for n in re.findall(r"(\d+) new registration outcomes saved to \S*local_sfm-", rerun))
    total = saved_outcomes(tmp_path)
    assert registered > 0 and before + registered == total  # only what the killed run had not saved

    # an uninterrupted run (features, matches and maps cached; every registration again) gives the same tables
    poses = next((tmp_path / ".cache" / "poses").glob("local_sfm-*"))
    poses.rename(poses.with_name("set-aside"))
    again = finished(evaluate(tmp_path, "uninterrupted"))
    assert f"{total} new registration outcomes saved" in again
    for name in TABLES:
        assert table(tmp_path / "rerun" / name) == table(tmp_path / "uninterrupted" / name), name
