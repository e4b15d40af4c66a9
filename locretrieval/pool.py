"""Independent tasks run in worker processes: the SfM stages', the report's figures', the renderer's.

Each `WorkerPool` is a loky process pool (fork+exec: pycolmap's, faiss's and torch's threads are
never forked, and the child does not re-apply the launcher's start method, which a job of Hydra's
joblib launcher sets to one a spawned child does not know), started on first use and kept for the
process: a worker spends seconds importing pycolmap or torch, which every later call would pay
again. A worker that dies is reported with its exit code (loky's `TerminatedWorkerError`), and
workers exit when the process that started them is gone (`exit_with_parent`). What loky does not
do: its `get_reusable_executor` keeps a single pool per process, and two serve at once here (the
SfM workers while the report's figure workers start), so each `WorkerPool` keeps its own loky
`ProcessPoolExecutor`; and its idle workers would hold up the exit of a process that
multiprocessing started (a joblib job), so a `WorkerPool` stops them first.

A small workload runs in this process (`runs_here`): starting workers costs more than they save.
The data that every task of a call shares is pickled once to a temporary file, which each worker
loads once per call. A caller may report progress in its own units (`progress_to`) and measure the
CPU time of its work, its tasks' in the workers included (`cpu_time`).
"""

from __future__ import annotations

import collections
import contextlib
import contextvars
import importlib
import math
import multiprocessing
import multiprocessing.util
import os
import pickle
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, TypeVar

from tqdm import tqdm

from locretrieval import limits
from locretrieval.threads import single_threaded

Task = TypeVar("Task")
Result = TypeVar("Result")

#: How often a worker checks that the process that started it is still alive.
PARENT_CHECK_SECONDS = 1.0
#: Fewer tasks than this per worker run in this process unless the pool is already started: starting
#: workers (seconds each) costs more than they save.
MIN_TASKS_PER_WORKER = 4
#: Seconds an idle pool keeps its workers (loky's timeout): a run's stages reuse them.
IDLE_SECONDS = 600
#: One BLAS/OpenMP thread per worker: the processes already use every core.
ONE_THREAD_ENVIRONMENT = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}


class WorkerPoolError(RuntimeError):
    """A worker process of a stage ended abruptly (killed, out of memory, or failed to start)."""


def available_cores() -> int:
    """The CPU cores this process may use: those its affinity allows (e.g. a SLURM job's share of a
    node), and in a process another Python process started (a job of Hydra's joblib launcher, which
    runs ``n_jobs`` at once), at most its ``OMP_NUM_THREADS``: joblib sets it to ``cores / n_jobs``
    there, so the jobs share the cores rather than each starting a worker per core."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    share = os.environ.get("OMP_NUM_THREADS", "")
    if multiprocessing.parent_process() is not None and share.isdigit() and int(share) > 0:
        cores = min(cores, int(share))
    return max(1, cores)


def resolve_workers(workers: int | None) -> int:
    """``workers`` as a positive count; ``None`` or 0 means one per core this process may use
    (`available_cores`)."""
    if workers is None or int(workers) == 0:
        return available_cores()
    if int(workers) < 0:
        raise ValueError(f"workers must be >= 0 (0 or null: one per core), got {workers}")
    return int(workers)


def task_size(items: int, cap: int, workers: int) -> int:
    """Items per task when ``items`` are split for ``workers`` processes: at most ``cap`` (e.g.
    what one shard file holds), fewer so that every worker gets one."""
    return max(1, min(cap, math.ceil(items / max(1, workers))))


def split(items: Sequence[Task], cap: int, workers: int) -> list[Sequence[Task]]:
    """``items`` in consecutive tasks of `task_size`."""
    size = task_size(len(items), cap, workers)
    return [items[start : start + size] for start in range(0, len(items), size)]


def exit_with_parent(parent: int) -> None:
    """A killed run's workers would otherwise go on writing to the cache: stop them, queued work
    included, once ``parent`` is gone."""
    while os.getppid() == parent:
        time.sleep(PARENT_CHECK_SECONDS)
    os._exit(1)


def _start_worker(
    parent: int, preload: tuple[str, ...], initializer: Callable[[], None] | None, budgets: limits.Limits
) -> None:
    """A worker's start: watch ``parent``, take its ``budgets`` (`locretrieval.limits`), import
    ``preload`` (what the first task would import, paid once when the pool starts), then ``initializer()``."""
    threading.Thread(target=exit_with_parent, args=(parent,), daemon=True).start()
    limits.use(budgets)
    for module in preload:
        importlib.import_module(module)
    if initializer is not None:
        initializer()


@dataclass
class CpuTime:
    """CPU seconds (user + system) of a block of work (`cpu_time`)."""

    seconds: float = 0.0


#: The `CpuTime` records the tasks finished in workers for the work in progress in this thread add to (`cpu_time`).
_cpu_records: contextvars.ContextVar[tuple[CpuTime, ...]] = contextvars.ContextVar("cpu_records", default=())


@contextlib.contextmanager
def cpu_time() -> Iterator[CpuTime]:
    """Within it, the CPU time of this process (every thread of it: stages that overlap in time share
    it) plus that of every task `WorkerPool.map` and `WorkerPool.stream` run for this thread in
    worker processes (measured there), added to the `CpuTime` it yields when the block ends (the
    workers' as their tasks finish). Blocks may nest: a task counts in each."""
    record, started = CpuTime(), time.process_time()
    token = _cpu_records.set((*_cpu_records.get(), record))
    try:
        yield record
    finally:
        _cpu_records.reset(token)
        record.seconds += time.process_time() - started


def _add_worker_cpu(seconds: float) -> None:
    """A worker task's CPU seconds, to every `cpu_time` block open in this thread."""
    for record in _cpu_records.get():
        record.seconds += seconds


#: The progress of the work in progress in this thread: ``advance(units)`` (`progress_to`).
_progress: contextvars.ContextVar[Callable[[int], None] | None] = contextvars.ContextVar("progress", default=None)


@contextlib.contextmanager
def progress_to(advance: Callable[[int], None]) -> Iterator[None]:
    """Within it, the calls of `WorkerPool.map` and `WorkerPool.stream` in this thread report each
    finished task's units (their ``units(task)``) to ``advance`` instead of a bar of their own."""
    token = _progress.set(advance)
    try:
        yield
    finally:
        _progress.reset(token)


def _one(task: Any) -> int:
    return 1


@contextlib.contextmanager
def _progress_of(description: str, tasks: int, units: Callable[[Any], int]) -> Iterator[Callable[[Any], None]]:
    """``done(task)``: to the caller's `progress_to`, else to a bar of ``tasks`` tasks."""
    advance = _progress.get()
    if advance is not None:
        yield lambda task: advance(units(task))
        return
    with tqdm(total=tasks, desc=description, unit="task", disable=None, leave=False) as bar:
        yield lambda task: bar.update()


def _call(function: Callable[..., Any], shared_file: str | None, task: Any) -> tuple[Any, float]:
    """In a worker: ``function(task)``, or ``function(shared, task)`` with the call's shared data
    loaded once per call; with the CPU seconds it took (loading included)."""
    started = time.process_time()
    if shared_file is None:
        return function(task), time.process_time() - started
    loaded = _call.__dict__.get("shared")
    if loaded is None or loaded[0] != shared_file:
        with open(shared_file, "rb") as stream:  # this process's own file (`_shared_file`), not a data file
            loaded = _call.__dict__["shared"] = (shared_file, pickle.load(stream))
    return function(loaded[1], task), time.process_time() - started


def _key(workers: int) -> tuple[int, str]:
    """An executor's key: its worker count and the budgets its workers take (`locretrieval.limits`)."""
    return workers, repr(limits.current())


class WorkerPool:
    """Worker processes of one purpose: ``name`` (errors name it), the modules each worker imports
    as it starts (``preload``) and an ``initializer`` (a module-level function) run after them;
    ``one_thread``: each worker's BLAS, OpenMP and torch on one thread. One loky pool per worker
    count and budgets (`locretrieval.limits.current`, which its workers take as they start), started on
    first use and kept."""

    def __init__(
        self,
        name: str,
        preload: Sequence[str] = (),
        initializer: Callable[[], None] | None = None,
        one_thread: bool = True,
    ) -> None:
        self.name, self.preload, self.initializer, self.one_thread = name, tuple(preload), initializer, one_thread
        self._executors: dict[tuple[int, str], Any] = {}
        self._lock = threading.Lock()  # the SfM pipeline submits from two threads
        # A process that multiprocessing started (a job of Hydra's joblib launcher) joins its children
        # as it exits, without running atexit: loky's idle workers would keep it waiting. Finalizers
        # of priority >= 0 run before that join: stop the workers there.
        multiprocessing.util.Finalize(self, WorkerPool.shutdown, args=(self,), exitpriority=100)

    def started(self, workers: int) -> bool:
        """Whether this pool's ``workers`` processes are running (with this process's budgets)."""
        return _key(workers) in self._executors

    def executor(self, workers: int) -> Any:
        """The loky executor of ``workers`` processes with this process's budgets, started now if it is not."""
        from loky import ProcessPoolExecutor

        key, budgets = _key(workers), limits.current()
        with self._lock:
            if key not in self._executors:
                self._executors[key] = ProcessPoolExecutor(
                    workers,
                    initializer=_start_worker,
                    initargs=(os.getpid(), self.preload, self.initializer, budgets),
                    env=ONE_THREAD_ENVIRONMENT if self.one_thread else None,
                    timeout=IDLE_SECONDS,
                )
            return self._executors[key]

    def start(self, workers: int) -> None:
        """Start ``workers`` processes now (e.g. while this process prepares what they will do)."""
        if workers > 1 and not self.started(workers):
            executor = self.executor(workers)
            for _ in range(workers):
                executor.submit(os.getpid)

    def submit(self, workers: int, function: Callable[..., Any], *args: Any, **kwargs: Any) -> Future:
        """A future of ``function(*args, **kwargs)`` in one of ``workers`` processes; a pool broken
        by an earlier call is replaced."""
        try:
            return self.executor(workers).submit(function, *args, **kwargs)
        except BrokenProcessPool:
            self._discard(workers)
            return self.executor(workers).submit(function, *args, **kwargs)

    def shutdown(self) -> None:
        """Stop every worker of this pool."""
        with self._lock:
            for executor in self._executors.values():
                executor.shutdown(wait=True, kill_workers=False)
            self._executors.clear()

    def _discard(self, workers: int) -> None:
        with self._lock:
            executor = self._executors.pop(_key(workers), None)
        if executor is not None:
            executor.shutdown(wait=False, kill_workers=True)

    def _broken(self, workers: int, stage: str, error: BaseException) -> WorkerPoolError:
        """The error of a call whose pool broke: naming ``stage`` and how its worker ended (loky's
        message holds the exit codes); the pool is discarded (the next call starts a new one)."""
        self._discard(workers)
        return WorkerPoolError(
            f"{stage}: a worker process ended abruptly ({_endings(str(error))}). SIGKILL usually means the machine "
            "ran out of memory (fewer workers: sfm.workers, data.render.workers); exit status 1 means the worker "
            "failed with the error printed above."
        )

    def runs_here(self, tasks: int, workers: int) -> bool:
        """Whether ``tasks`` tasks run in this process rather than in ``workers`` worker processes:
        one worker, one task, or fewer than `MIN_TASKS_PER_WORKER` tasks per worker while no pool of
        that size is started."""
        return workers == 1 or tasks <= 1 or (not self.started(workers) and tasks < MIN_TASKS_PER_WORKER * workers)

    def map(
        self,
        function: Callable[..., Result],
        tasks: Sequence[Task],
        workers: int | None,
        description: str,
        shared: Any = None,
        units: Callable[[Task], int] = _one,
    ) -> Iterator[Result]:
        """``function(task)``, or ``function(shared, task)`` when ``shared`` is given, for every
        task, in order, with progress (each task's ``units``, `progress_to`).

        `runs_here` decides where: in this process each task runs single-threaded, as a worker
        runs it (one thread is faster on such tasks than several sharing them). ``function`` must
        be a module-level function and ``shared``, the tasks and the results picklable."""
        workers = resolve_workers(workers)
        with _progress_of(description, len(tasks), units) as done:
            if self.runs_here(len(tasks), workers):
                for task in tasks:
                    with single_threaded():
                        result = function(task) if shared is None else function(shared, task)
                    done(task)
                    yield result
                return
            with _shared_file(shared) as shared_file:
                try:
                    results = self.executor(workers).map(partial(_call, function, shared_file), tasks, chunksize=1)
                    for task, (result, seconds) in zip(tasks, results):
                        _add_worker_cpu(seconds)
                        done(task)
                        yield result
                except BrokenProcessPool as error:
                    raise self._broken(workers, description, error) from error

    @contextlib.contextmanager
    def stream(
        self,
        function: Callable[..., Any],
        tasks: int,
        workers: int | None,
        description: str,
        shared: Any = None,
        units: Callable[[Any], int] = _one,
    ) -> Iterator[Callable[[Any], None]]:
        """``submit(task)`` hands ``function(shared, task)`` (or ``function(task)``) to the workers
        and returns at once, so the caller goes on producing tasks (e.g. a GPU matching while the
        CPUs verify); at most two tasks per worker wait at a time (the caller blocks on the oldest
        beyond that). Leaving the block waits for every task and raises the first error. With
        ``tasks`` expected that `runs_here`, each task runs in this process when it is submitted."""
        workers = resolve_workers(workers)
        with _progress_of(description, tasks, units) as done:
            if self.runs_here(tasks, workers):

                def run_here(task: Any) -> None:
                    with single_threaded():
                        function(task) if shared is None else function(shared, task)
                    done(task)

                yield run_here
                return
            executor, pending = self.executor(workers), collections.deque()

            def finish_oldest() -> None:
                task, future = pending.popleft()
                _add_worker_cpu(future.result()[1])
                done(task)

            with _shared_file(shared) as shared_file:

                def submit(task: Any) -> None:
                    while len(pending) >= 2 * workers:
                        finish_oldest()
                    pending.append((task, executor.submit(_call, function, shared_file, task)))

                try:
                    yield submit
                    while pending:
                        finish_oldest()
                except BrokenProcessPool as error:
                    raise self._broken(workers, description, error) from error
                finally:
                    for _, future in pending:
                        future.cancel()


def _endings(message: str) -> str:
    """How the workers ended, from loky's message (e.g. ``{SIGKILL(-9)}``): signal names or exit statuses."""
    codes = [int(code) for code in _exit_codes(message)]
    if not codes:
        return "exit status unknown"
    return ", ".join(
        sorted({f"ended by {_signal_name(-code)}" if code < 0 else f"exit status {code}" for code in codes})
    )


def _exit_codes(message: str) -> list[str]:
    import re

    return re.findall(r"\((-?\d+)\)", message.partition("exit codes of the workers are")[2])


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


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


def _one_thread_worker() -> None:
    """A compute worker's start: BLAS and torch on one thread (the processes already use every
    core), and no final garbage collection at exit (seconds over the caches' objects)."""
    import threadpoolctl
    import torch

    import locretrieval

    locretrieval.exit_without_final_collection()
    threadpoolctl.threadpool_limits(1)
    torch.set_num_threads(1)


#: The compute workers of this process, shared by the renderer and the SfM stages (one pool: a
#: worker's start, seconds of imports, is paid once per run). Each imports, as it starts, what their
#: first tasks would: locretrieval (zlib before pycolmap), pycolmap, torch and the SfM stages' modules.
WORKERS = WorkerPool(
    "workers",
    preload=("locretrieval", "pycolmap", "torch", "locretrieval.sfm.pipeline"),
    initializer=_one_thread_worker,
)
