"""Start contexts of the project's process pools and DataLoaders, chosen here and never inherited
from whatever launched this process (a plain run, a job of Hydra's joblib or submitit launcher).

A spawned child re-applies its parent's global start method before it runs anything else
(``multiprocessing.spawn.prepare``). Inside a job of Hydra's joblib launcher that method is
``loky``, which the child does not know (it has not imported loky), so it dies before its first
task and the pool breaks. `spawn_context` resets such a foreign global method to ``spawn`` (loky's
own executor names its context explicitly and is not affected); DataLoaders are given a context
explicitly (`dataloader_context`) instead of the launcher's.
"""

from __future__ import annotations

import multiprocessing
import signal
from concurrent.futures import ProcessPoolExecutor
from multiprocessing.context import BaseContext

#: The start method of DataLoader workers: fork (PyTorch's default on Linux; the dataset is not
#: pickled and a worker starts in milliseconds), spawn where the platform has no fork.
DATALOADER_START_METHOD = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"


class WorkerPoolError(RuntimeError):
    """A worker process of a stage ended abruptly (killed, out of memory, or failed to start)."""


def spawn_context() -> BaseContext:
    """The ``spawn`` context for a process pool, with this process's global start method made one
    that a spawned child can re-apply (``loky`` inside a joblib launcher's job is not)."""
    method = multiprocessing.get_start_method(allow_none=True)
    if method is not None and method not in multiprocessing.get_all_start_methods():  # unset: left so
        multiprocessing.set_start_method("spawn", force=True)
    return multiprocessing.get_context("spawn")


def dataloader_context(num_workers: int) -> BaseContext | None:
    """The start context of a DataLoader with ``num_workers`` processes (None: no processes)."""
    if num_workers == 0:
        return None
    spawn_context()  # a spawn DataLoader's children re-apply the global method too
    return multiprocessing.get_context(DATALOADER_START_METHOD)


def broken_pool_error(pool: ProcessPoolExecutor, stage: str) -> WorkerPoolError:
    """A `WorkerPoolError` naming ``stage`` and how its workers ended (their exit codes: a
    signal's name for a negative one), for a pool that raised ``BrokenProcessPool``."""
    processes = getattr(pool, "_processes", None) or {}  # the executor keeps its workers there
    endings = sorted({_ending(process.exitcode) for process in processes.values()})
    return WorkerPoolError(
        f"{stage}: a worker process ended abruptly ({', '.join(endings) or 'exit status unknown'}). "
        "SIGKILL usually means the machine ran out of memory (fewer workers: sfm.workers, "
        "data.render.workers); exit status 1 means the worker failed with the error printed above."
    )


def _ending(exitcode: int | None) -> str:
    if exitcode is None:
        return "still running"
    if exitcode < 0:
        try:
            return f"ended by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"ended by signal {-exitcode}"
    return f"exit status {exitcode}"
