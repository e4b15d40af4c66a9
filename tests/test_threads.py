"""The same numbers on any machine: ``evaluate.py`` run with 1, 2 and 4 threads of every threaded
library (torch, BLAS/OpenMP, faiss, numba) fits the same DenseVLAD, caches the same descriptors,
ranks the same images with the same scores and writes the same tables, byte for byte."""

import gzip
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: 24 queries: faiss searches 20 or more queries at once with a BLAS product (fewer: one by one).
#: 16 database images: enough for local maps of 3 and a global map. The scene is rendered once, in
#: the 1-thread run's own process (workers=1: no pool of renderers to start), and copied for the
#: others (rendering is checked elsewhere). 100 bootstrap resamples and a vocabulary from 20,000
#: RootSIFTs (5 k-means chunks of 4,096, which the threads share out) in 10 iterations: the same
#: threaded code at a fraction of the default's work. The SfM in each run's own process (sfm.workers=1):
#: its tasks run on one thread wherever they run, and a pool's workers (seconds of imports each) would
#: add nothing to the comparison of thread counts.
COMMAND = [
    "data.render.width=160",
    "data.render.height=120",
    "data.render.num_database=16",
    "data.render.num_queries=24",
    "data.render.workers=1",
    "data.render.texture_size=64",
    "data.render.length=20.0",
    "data.render.seed=7",
    "model.max_side=160",
    "model.step=4",
    "model.vocabulary_samples=20000",
    "model.kmeans_iterations=10",
    "metrics.uncertainty.resamples=100",
    "subsets.blur_width=160",
    "sfm.workers=1",
    "paradigms.local_sfm.k=[3]",
    "paradigms.global_sfm.k=[1,3]",
    "output.ltvl=false",
    "report.figure_formats=[]",
    "report.scene_view.enabled=false",
]
TABLES = ("results.csv", "query_errors.csv.gz", "estimated_poses.csv.gz", "retrieval.csv", "median_errors.csv")
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")
pytestmark = pytest.mark.slow


def evaluate(root: Path, threads: int) -> Path:
    """The run folder of ``evaluate.py`` with every library limited to ``threads``."""
    environment = {**os.environ, **{variable: str(threads) for variable in THREAD_VARIABLES}}
    completed = subprocess.run(
        [
            sys.executable,
            str(ROOT / "evaluate.py"),
            f"paths.root_dir={root}",
            f"hydra.run.dir={root / 'run'}",
            *COMMAND,
        ],
        cwd=ROOT,
        env=environment,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    return root / "run"


def contents(path: Path) -> bytes:
    return gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()


def test_descriptors_rankings_and_tables_do_not_depend_on_the_thread_count(tmp_path):
    runs = {1: evaluate(tmp_path / "1", 1)}
    for threads in (2, 4):  # the same rendered scene (rendering is checked elsewhere): its descriptors anew
        shutil.copytree(tmp_path / "1" / ".cache" / "synthetic", tmp_path / str(threads) / ".cache" / "synthetic")
        runs[threads] = evaluate(tmp_path / str(threads), threads)
    descriptors = {
        threads: [contents(path) for path in sorted((tmp_path / str(threads) / ".cache" / "descriptors").glob("*"))]
        for threads in runs
    }
    rankings = {
        threads: [contents(path) for path in sorted((run / "rankings").glob("*.npz"))] for threads, run in runs.items()
    }
    assert len(descriptors[1]) >= 1 and len(rankings[1]) >= 4
    for threads, run in runs.items():
        assert descriptors[threads] == descriptors[1], threads
        assert rankings[threads] == rankings[1], threads
        for name in TABLES:
            assert contents(run / name) == contents(runs[1] / name), (threads, name)


SEARCH = """
import hashlib, sys
import numpy as np
from locretrieval.retrieval.index import search
rng = np.random.default_rng(0)
queries, database = (rng.standard_normal((rows, 512)).astype(np.float32) for rows in (300, 2000))
ranking = search(queries, database, 50, "random", 1024)
print(hashlib.sha256(ranking.indices.tobytes() + ranking.scores.tobytes()).hexdigest())
"""


def test_a_search_large_enough_for_threaded_blas_ranks_the_same_with_1_2_and_4_threads():
    """300 x 2000 descriptors of 512 dimensions: OpenBLAS splits such a product over its threads."""
    digests = set()
    for threads in (1, 2, 4):
        environment = {**os.environ, **{variable: str(threads) for variable in THREAD_VARIABLES}}
        done = subprocess.run(
            [sys.executable, "-c", SEARCH], env=environment, capture_output=True, text=True, timeout=300
        )
        assert done.returncode == 0, done.stderr[-2000:]
        digests.add(done.stdout.strip())
    assert len(digests) == 1


def test_a_single_threaded_block_gives_torch_back_its_threads():
    """A block that limits every library to one thread leaves torch with the threads it had: a
    DenseVLAD fit (k-means in such a block) then describes on every core."""
    import torch

    from locretrieval.threads import single_threaded

    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with single_threaded():
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(previous)
