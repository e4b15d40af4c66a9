"""Run independent tasks in worker processes (spawned: pycolmap, faiss and torch keep threads).

Starting a worker costs seconds (it imports the entry point's modules and pycolmap), so one
pool per worker count is started on first use and reused by every later call of this process. The data
that all tasks of a call share is pickled once to a temporary file, and each worker loads
it once per call.
"""

from __future__ import annotations

import collections
import contextlib
import copy
import math
import multiprocessing.util
import os
import pickle
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

from tqdm import tqdm

from locretrieval.processes import broken_pool_error, spawn_context
from locretrieval.threads import single_threaded

Task = TypeVar("Task")
Result = TypeVar("Result")

#: How often a worker checks that the process that started it is still alive.
PARENT_CHECK_SECONDS = 1.0
#: Fewer tasks than this per worker run in this process unless the pool is already started: starting
#: workers (seconds each) costs more than they save (a 4-query scene: 20 s in-process, 28 s with two).
MIN_TASKS_PER_WORKER = 4
#: In a worker: (file, object) of the shared data of the call in progress.
_shared: tuple[str, Any] | None = None
#: Whether the calls run in this process start from their shared inputs loaded afresh (`as_workers_load_it`).
_fresh_shared = False


def resolve_workers(workers: int | None) -> int:
    """``workers`` as a positive count; ``None`` or 0 means one per CPU core."""
    if workers is None or int(workers) == 0:
        return os.cpu_count() or 1
    if int(workers) < 0:
        raise ValueError(f"workers must be >= 0 (0 or null: one per core), got {workers}")
    return int(workers)


def _initialize_worker(parent: int) -> None:
    """Exit with the ``parent`` process (watched before the slow imports, so a parent that dies
    while its workers start is noticed); one BLAS/OpenMP thread per worker (the processes
    already use every core)."""
    threading.Thread(target=exit_with_parent, args=(parent,), daemon=True).start()
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = (
        "1"  # torch reads them when it is imported (matching)
    )
    import threadpoolctl

    import locretrieval  # (imports zlib before pycolmap)

    locretrieval.exit_without_final_collection()
    threadpoolctl.threadpool_limits(1)
    import pycolmap

    pycolmap.logging.minloglevel = 2
    # the SfM stages' modules (h5py, scipy, the triangulators, torch for matching), which their first
    # task would import: seconds a worker spends once, when the pool starts rather than in a stage
    import torch

    import locretrieval.sfm.pipeline  # noqa: F401

    torch.set_num_threads(1)


def exit_with_parent(parent: int) -> None:
    """A killed run's workers would wait for tasks forever (they hold their queue's both ends)
    and go on writing to the cache: stop them, queued work included, once ``parent`` is gone."""
    while os.getppid() == parent:
        time.sleep(PARENT_CHECK_SECONDS)
    os._exit(1)


def _call(function: Callable[..., Any], shared_file: str | None, task: Any) -> Any:
    global _shared
    if shared_file is None:
        return function(task)
    if _shared is None or _shared[0] != shared_file:
        with open(shared_file, "rb") as stream:
            _shared = (shared_file, pickle.load(stream))
    return function(_shared[1], task)


class SpawnedPools:
    """This process's pools of spawned workers (torch and faiss keep threads: no fork), one per
    worker count, started on first use and kept; ``initializer(parent pid)`` runs in each worker."""

    def __init__(self, initializer: Callable[[int], None]) -> None:
        self.initializer = initializer
        self.pools: dict[int, ProcessPoolExecutor] = {}
        self._lock = threading.Lock()  # the SfM pipeline submits from two threads
        # A process that multiprocessing started (a job of Hydra's joblib launcher) joins its
        # children as it exits, before the interpreter would shut these pools down: shut them
        # down first (finalizers of priority >= 0 run before that join, highest first; above the
        # pools' own queues', 10, whose feeder threads must still send the workers their stop).
        multiprocessing.util.Finalize(self, SpawnedPools.shutdown, args=(self,), exitpriority=100)

    def shutdown(self) -> None:
        """Stop every pool's workers (they exit when told, or with this process)."""
        with self._lock:
            for pool in self.pools.values():
                pool.shutdown(wait=True, cancel_futures=True)
            self.pools.clear()

    def started(self, workers: int) -> bool:
        return workers in self.pools

    def get(self, workers: int) -> ProcessPoolExecutor:
        with self._lock:
            if workers not in self.pools:
                self.pools[workers] = ProcessPoolExecutor(
                    workers, mp_context=spawn_context(), initializer=self.initializer, initargs=(os.getpid(),)
                )
            return self.pools[workers]

    def discard(self, workers: int, stage: str) -> Exception:
        """Shut a broken pool down (the next `get` starts a new one); the error to raise, naming
        ``stage`` and how its workers ended."""
        pool = self.pools.pop(workers)
        pool.shutdown(cancel_futures=True)
        return broken_pool_error(pool, stage)


#: The SfM workers of this process.
_pools = SpawnedPools(_initialize_worker)


def runs_here(tasks: int, workers: int, started: bool | None = None) -> bool:
    """Whether `parallel_map` and `task_stream` run ``tasks`` tasks in this process rather than
    in ``workers`` worker processes: one worker, one task, or a small workload (fewer than
    `MIN_TASKS_PER_WORKER` tasks per worker) while no pool of that size is started (``started``:
    whether one is, None: this process's pools tell)."""
    started = workers_started(workers) if started is None else started
    return workers == 1 or tasks <= 1 or (not started and tasks < MIN_TASKS_PER_WORKER * workers)


def task_size(items: int, cap: int, workers: int) -> int:
    """Items per task when ``items`` are split for ``workers`` processes: at most ``cap`` (e.g.
    what one shard file holds), fewer so that every worker gets one."""
    return max(1, min(cap, math.ceil(items / max(1, workers))))


def split(items: Sequence[Task], cap: int, workers: int) -> list[Sequence[Task]]:
    """``items`` in consecutive tasks of `task_size`."""
    size = task_size(len(items), cap, workers)
    return [items[start : start + size] for start in range(0, len(items), size)]


def workers_started(workers: int) -> bool:
    """Whether this process's pool of ``workers`` processes is running."""
    return _pools.started(workers)


def start_workers(workers: int) -> float:
    """Start this process's pool of ``workers`` processes now, each through its initializer;
    the seconds it took (0 when it was started already)."""
    if workers == 1 or _pools.started(workers):
        return 0.0
    started, answered = time.perf_counter(), set()
    pool = _pools.get(workers)
    while len(answered) < workers:  # until every worker has answered: each one is past its initializer
        answered.update(future.result() for future in [pool.submit(_worker_pid) for _ in range(workers)])
    return time.perf_counter() - started


def _worker_pid() -> int:
    time.sleep(0.01)  # long enough for the other workers to take their tasks
    return os.getpid()


def parallel_map(
    function: Callable[..., Result], tasks: Sequence[Task], workers: int | None, description: str, shared: Any = None
) -> Iterator[Result]:
    """``function(task)``, or ``function(shared, task)`` when ``shared`` is given, for every
    task, in order, with a progress bar.

    ``workers == 1``, a single task, or a small workload (fewer than `MIN_TASKS_PER_WORKER`
    tasks per worker while no pool is started) runs in this process, single-threaded as a worker
    runs it (one thread is faster on such tasks than several sharing them, and their costs are
    the same either way); otherwise this process's pool of spawned workers runs them.
    ``function`` must be a module-level function and ``shared``, the tasks and the results picklable.
    """
    workers = resolve_workers(workers)
    progress: Any = tqdm(total=len(tasks), desc=description, unit="task", disable=None, leave=False)
    with progress:
        if runs_here(len(tasks), workers):
            shared = _loaded_here(shared) if len(tasks) else shared
            for task in tasks:
                with single_threaded():  # as a worker runs it: threads are slower than one on such tasks
                    result = function(task) if shared is None else function(shared, task)
                yield result
                progress.update()
            return
        with _shared_file(shared) as shared_file:
            try:
                for result in _pools.get(workers).map(partial(_call, function, shared_file), tasks, chunksize=1):
                    yield result
                    progress.update()
            except BrokenProcessPool as error:
                raise _pools.discard(workers, description) from error


@contextlib.contextmanager
def as_workers_load_it() -> Iterator[None]:
    """Within it, each `parallel_map` or `task_stream` call run in this process starts from a copy
    of its ``shared`` inputs made by their pickling state, as every worker loads them at each call
    (the stores' in-memory shards empty: `ShardedStore.__getstate__`), so that a call's cost in a
    worker is timed here (the SfM forecast's sample, run in one process)."""
    global _fresh_shared
    previous, _fresh_shared = _fresh_shared, True
    try:
        yield
    finally:
        _fresh_shared = previous


def _loaded_here(shared: Any) -> Any:
    """``shared`` as a worker loads it (`as_workers_load_it`), else itself."""
    if not _fresh_shared or shared is None:
        return shared
    return copy.deepcopy(shared)  # by `__getstate__`, as pickle: no unpickling of bytes


@contextlib.contextmanager
def task_stream(
    function: Callable[..., Any], tasks: int, workers: int | None, description: str, shared: Any = None
) -> Iterator[Callable[[Any], None]]:
    """``submit(task)`` hands ``function(shared, task)`` (or ``function(task)``) to this process's
    worker pool and returns at once, so the caller goes on producing tasks (e.g. a GPU matching
    while the CPUs verify); at most two tasks per worker wait at a time (the caller blocks on the
    oldest beyond that). Leaving the block waits for every task and raises the first error.
    ``workers == 1``, or a small workload (as `parallel_map` judges it from the ``tasks`` expected),
    runs each task in this process when it is submitted."""
    workers = resolve_workers(workers)
    progress: Any = tqdm(total=tasks, desc=description, unit="task", disable=None, leave=False)
    with progress:
        if runs_here(tasks, workers):
            shared = _loaded_here(shared) if tasks else shared

            def run_here(task: Any) -> None:
                with single_threaded():
                    function(task) if shared is None else function(shared, task)
                progress.update()

            yield run_here
            return
        pool, pending = _pools.get(workers), collections.deque()
        with _shared_file(shared) as shared_file:

            def submit(task: Any) -> None:
                while len(pending) >= 2 * workers:
                    pending.popleft().result()
                    progress.update()
                pending.append(pool.submit(_call, function, shared_file, task))

            try:
                yield submit
                while pending:
                    pending.popleft().result()
                    progress.update()
            except BrokenProcessPool as error:
                raise _pools.discard(workers, description) from error
            finally:
                for future in pending:
                    future.cancel()


@contextlib.contextmanager
def _shared_file(shared: Any) -> Iterator[str | None]:
    """``shared`` pickled once into a temporary file the workers load (None: nothing shared)."""
    if shared is None:
        yield None
        return
    with tempfile.TemporaryDirectory(prefix="locretrieval-shared-") as folder:
        shared_file = str(Path(folder) / "shared.pickle")
        with open(shared_file, "wb") as stream:
            pickle.dump(shared, stream, protocol=pickle.HIGHEST_PROTOCOL)
        yield shared_file
