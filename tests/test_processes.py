"""Worker pools (`locretrieval.pool`): small workloads stay in this process, a worker's death names
the stage and its signal, progress counts each task's units, and a pool runs inside a joblib job.

The tasks below are this module's functions, which every worker process (and every job of the joblib
scripts) imports to unpickle them: the module imports no torch (seconds of CPU per process; torch only
in the tests that use it), so each worker start costs what a worker of the tested pool costs, not torch's import.
"""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from locretrieval.pool import MIN_TASKS_PER_WORKER, WorkerPool, WorkerPoolError, cpu_time, progress_to
from locretrieval.processes import dataloader_workers


def process_id(shared, task):
    return shared, task, os.getpid()


def test_a_small_workload_runs_in_this_process_without_starting_workers():
    pool = WorkerPool("test")
    few = MIN_TASKS_PER_WORKER * 2 - 1  # below the threshold for two workers
    results = list(pool.map(process_id, list(range(few)), 2, "test", shared="s"))
    assert results == [("s", task, os.getpid()) for task in range(few)]
    assert not pool.started(2)  # no worker was started


@pytest.mark.parametrize("count", [3, MIN_TASKS_PER_WORKER * 2])  # in this process, in two workers
def test_each_finished_task_reports_its_units_to_the_progress_of_its_stage(count):
    pool, done = WorkerPool("test"), []
    tasks = [list(range(size)) for size in range(1, count + 1)]
    with progress_to(done.append):
        results = pool.map(process_id, tasks, 2, "test", shared="s", units=len)
        first = next(results)
        assert done == [1]  # counted as the task's result is handed over, not after the caller asks for the next
        rest = list(results)
    assert [task for _, task, _ in [first, *rest]] == tasks
    assert done == list(range(1, count + 1)) and sum(done) == count * (count + 1) // 2
    assert pool.started(2) == (count >= MIN_TASKS_PER_WORKER * 2)
    pool.shutdown()


def record(task):
    return task


def test_a_stream_reports_each_task_it_finished():
    pool, done = WorkerPool("test"), []
    with progress_to(done.append), pool.stream(record, 8, 2, "test", units=lambda task: task) as submit:
        for task in range(8):
            submit(task)
    assert sorted(done) == list(range(8)) and pool.started(2)
    pool.shutdown()


def busy(shared, seconds):
    """Burn ``seconds`` of this process's CPU time."""
    started = time.process_time()
    while time.process_time() - started < seconds:
        pass
    return seconds


def test_the_cpu_time_of_a_block_holds_its_tasks_cpu_time_in_the_workers():
    pool = WorkerPool("test")
    tasks = [0.05] * (MIN_TASKS_PER_WORKER * 2)  # enough to start two workers
    here = time.process_time()
    with cpu_time() as outer:
        with cpu_time() as inner:
            finished = list(pool.map(busy, tasks, 2, "test", shared="s"))
        with pool.stream(busy, len(tasks), 2, "test", shared="s") as submit:
            for task in tasks:
                submit(task)
    here = time.process_time() - here  # this process's own CPU time, both blocks included
    assert finished == tasks and pool.started(2)
    # each task burnt its 0.05 s in a worker, counted in the block it ran for and in the one around it
    assert sum(tasks) <= inner.seconds <= sum(tasks) + 0.1 + here
    assert 2 * sum(tasks) <= outer.seconds <= 2 * sum(tasks) + 0.2 + here
    pool.shutdown()


def killed_in_a_worker(task):
    if task == 3:
        os.kill(os.getpid(), signal.SIGKILL)  # as the out-of-memory killer ends a process
    return task


def test_a_worker_killed_mid_stage_is_an_error_naming_the_stage_and_the_signal():
    pool = WorkerPool("test")
    tasks = list(range(MIN_TASKS_PER_WORKER * 2))  # enough for the pool of two workers
    with pytest.raises(WorkerPoolError, match=r"^triangulate \+ register: a worker process ended abruptly \(.*SIGKILL"):
        list(pool.map(killed_in_a_worker, tasks, 2, "triangulate + register"))
    assert not pool.started(2)  # the broken pool is gone: the next call starts a new one
    assert list(pool.map(killed_in_a_worker, [0, 1, 2] * 3, 2, "again")) == [0, 1, 2] * 3
    pool.shutdown()


def pool_results_in_a_job():
    """Two workers' results, from a process of joblib's loky executor (a job of Hydra's joblib launcher)."""
    from locretrieval.pool import WORKERS

    return os.getpid(), list(WORKERS.map(process_id, list(range(8)), 2, "in a joblib job", shared="s"))


JOBLIB_JOB = """
import sys
sys.path.insert(0, sys.argv[1])
from joblib import Parallel, delayed
import test_processes
((job, results),) = Parallel(n_jobs=2, backend="loky")([delayed(test_processes.pool_results_in_a_job)()])
assert [task for _, task, _ in results] == list(range(8)), results
assert job not in {pid for *_, pid in results}  # the job's own worker processes ran them
print("done")
"""


def test_the_compute_workers_run_inside_a_job_of_joblibs_loky_executor_and_let_it_exit():
    """The compute pool starts in a loky process (whose start method a spawned child would not know),
    and the job's process exits afterwards."""
    done = subprocess.run(
        [sys.executable, "-c", JOBLIB_JOB, str(Path(__file__).parent)], capture_output=True, text=True, timeout=180
    )
    assert done.returncode == 0 and done.stdout.strip() == "done", done.stderr[-3000:]


def workers_of_a_job():
    """What a job of joblib's loky executor (Hydra's joblib launcher) resolves ``sfm.workers`` null and 3 to."""
    from locretrieval.pool import resolve_workers

    return resolve_workers(None), resolve_workers(3)


JOBLIB_SHARES = """
import os, sys
sys.path.insert(0, sys.argv[1])
from joblib import Parallel, delayed
from locretrieval.pool import resolve_workers
import test_processes
jobs = Parallel(n_jobs=2, backend="loky")(delayed(test_processes.workers_of_a_job)() for _ in range(2))
print(resolve_workers(None), *jobs)
"""


def test_the_jobs_of_a_launcher_that_runs_two_at_once_share_the_cores_instead_of_a_worker_per_core_each():
    environment = {name: value for name, value in os.environ.items() if not name.endswith("_NUM_THREADS")}
    done = subprocess.run(
        [sys.executable, "-c", JOBLIB_SHARES, str(Path(__file__).parent)],
        capture_output=True,
        text=True,
        timeout=180,
        env=environment,
    )
    cores = len(os.sched_getaffinity(0))
    # a plain process: every core it may use; each of two jobs: half of them (joblib's OMP_NUM_THREADS), at least one
    assert done.stdout.split() == [str(cores), *[f"({max(1, cores // 2)},", "3)"] * 2], done.stderr[-3000:]


def test_dataloader_workers_leave_a_plain_process_s_start_method_alone_and_take_its_budgets():
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            "import multiprocessing\nfrom locretrieval.processes import dataloader_workers\n"
            "options = dataloader_workers(2)\nprint(multiprocessing.get_start_method(allow_none=True))",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=Path(__file__).parents[1],
    )
    assert done.stdout.strip() == "None", done.stderr  # other libraries' pools keep their platform default


class Budgets:
    """Each item: the image budget its worker process sees (`locretrieval.limits.current`). A map-style
    dataset as the DataLoader reads one (``__len__`` and ``__getitem__``), not a subclass of torch's
    `Dataset`: this module imports no torch (see the module's docstring)."""

    def __len__(self) -> int:
        return 4

    def __getitem__(self, index: int) -> int:
        from locretrieval import limits

        return limits.current().image_pixels


def image_budget(_: int) -> int:
    from locretrieval import limits

    return limits.current().image_pixels


def test_the_run_s_budgets_reach_every_worker_with_its_start(monkeypatch):
    """The budgets the build step sets (`limits.use`) are what two DataLoader workers and two pool
    workers read, not the defaults: they are handed over as the workers start."""
    import torch
    from helpers import set_limits

    set_limits(monkeypatch, image_pixels=12345)
    loader = torch.utils.data.DataLoader(Budgets(), batch_size=None, **dataloader_workers(2))
    assert sorted(int(value) for value in loader) == [12345] * 4
    pool = WorkerPool("budgets test")
    try:
        assert list(pool.executor(2).map(image_budget, range(4))) == [12345] * 4
    finally:
        pool.shutdown()
