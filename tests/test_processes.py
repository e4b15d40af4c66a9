"""Worker processes: small workloads stay in this process."""

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from locretrieval.processes import WorkerPoolError
from locretrieval.sfm import workers


def process_id(shared, task):
    return shared, task, os.getpid()


def test_a_small_workload_runs_in_this_process_without_starting_workers(monkeypatch):
    monkeypatch.setattr(workers, "_pools", workers.SpawnedPools(workers._pools.initializer))
    few = workers.MIN_TASKS_PER_WORKER * 2 - 1  # below the threshold for two workers
    results = list(workers.parallel_map(process_id, list(range(few)), 2, "test", shared="s"))
    assert results == [("s", task, os.getpid()) for task in range(few)]
    assert workers._pools.pools == {}  # no worker was spawned


def store_cache_size(store, task):
    return store, len(store._cache)


#: What `record_cache_size` saw (a task of `task_stream` returns nothing).
SEEN = []


def record_cache_size(store, task):
    SEEN.append(store_cache_size(store, task))


def test_calls_run_here_can_start_from_their_inputs_as_a_worker_loads_them(tmp_path, monkeypatch):
    """`as_workers_load_it` (the SfM forecast's sample): each call's tasks get one copy of the shared
    inputs, its stores' in-memory shards empty; outside it, the inputs themselves."""
    from locretrieval.sfm.store import ShardedStore

    monkeypatch.setattr(workers, "_pools", workers.SpawnedPools(workers._pools.initializer))
    store = ShardedStore(tmp_path)
    store._cache[(tmp_path / "shard", "data")] = {"key": None}  # a shard read before
    plain = list(workers.parallel_map(store_cache_size, [0, 1], 1, "test", store))
    assert plain == [(store, 1), (store, 1)]
    with workers.as_workers_load_it():
        fresh = list(workers.parallel_map(store_cache_size, [0, 1], 1, "test", store))
        SEEN.clear()
        with workers.task_stream(record_cache_size, 2, 1, "test", store) as submit:
            submit(0)
            submit(1)
    assert [size for _, size in fresh] == [0, 0] and fresh[0][0] is fresh[1][0] is not store
    assert [size for _, size in SEEN] == [0, 0] and SEEN[0][0] is SEEN[1][0] is not store
    assert len(store._cache) == 1 and not workers._fresh_shared and workers._pools.pools == {}


def killed_in_a_worker(task):
    if task == 3:
        os.kill(os.getpid(), signal.SIGKILL)  # as the out-of-memory killer ends a process
    return task


def test_a_worker_killed_mid_stage_is_an_error_naming_the_stage_and_the_signal(monkeypatch):
    monkeypatch.setattr(workers, "_pools", workers.SpawnedPools(workers._pools.initializer))
    tasks = list(range(workers.MIN_TASKS_PER_WORKER * 2))  # enough for the pool of two workers
    with pytest.raises(WorkerPoolError, match=r"^triangulate \+ register: a worker process ended abruptly \(.*SIGKILL"):
        list(workers.parallel_map(killed_in_a_worker, tasks, 2, "triangulate + register"))
    assert workers._pools.pools == {}  # the broken pool is gone: the next call starts a new one
    assert list(workers.parallel_map(killed_in_a_worker, [0, 1, 2] * 3, 2, "again")) == [0, 1, 2] * 3


def spawned_pool_results():
    """Two workers' results, from a process of joblib's loky executor (a job of Hydra's joblib launcher)."""
    return os.getpid(), list(workers.parallel_map(process_id, list(range(8)), 2, "in a joblib job", shared="s"))


JOBLIB_JOB = """
import sys
sys.path.insert(0, sys.argv[1])
from joblib import Parallel, delayed
import test_processes
((job, results),) = Parallel(n_jobs=2, backend="loky")([delayed(test_processes.spawned_pool_results)()])
assert [task for _, task, _ in results] == list(range(8)), results
assert job not in {pid for *_, pid in results}  # the job's own worker processes ran them
print("done")
"""


def test_the_worker_pool_runs_inside_a_job_of_joblibs_loky_executor_and_lets_it_exit():
    """The pool starts in a loky process (whose start method no spawned child knows), and the job's
    process exits afterwards: multiprocessing joins a child's children before the interpreter
    would stop their pools, so the pools are stopped first (it used to wait forever)."""
    done = subprocess.run(
        [sys.executable, "-c", JOBLIB_JOB, str(Path(__file__).parent)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0 and done.stdout.strip() == "done", done.stderr[-3000:]


def test_starting_a_pool_leaves_a_plain_process_s_start_method_alone():
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            "import multiprocessing\nfrom locretrieval.processes import spawn_context\nspawn_context()\n"
            "print(multiprocessing.get_start_method(allow_none=True))",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=Path(__file__).parents[1],
    )
    assert done.stdout.strip() == "None", done.stderr  # other libraries' pools keep their platform default
