"""Start contexts of the DataLoaders' worker processes, chosen here and never inherited from
whatever launched this process (a plain run, a job of Hydra's joblib or submitit launcher).

A spawned child re-applies its parent's global start method before it runs anything else
(``multiprocessing.spawn.prepare``). Inside a job of Hydra's joblib launcher that method is
``loky``, which the child does not know (it has not imported loky), so it dies before its first
task. `spawn_context` resets such a foreign global method to ``spawn``; DataLoaders are given a
context explicitly (`dataloader_workers`). The project's own pools are loky's (`locretrieval.pool`).
"""

from __future__ import annotations

import functools
import multiprocessing
from multiprocessing.context import BaseContext
from typing import Any

from locretrieval import limits

#: The start method of DataLoader workers: fork (PyTorch's default on Linux; the dataset is not
#: pickled and a worker starts in milliseconds), spawn where the platform has no fork.
DATALOADER_START_METHOD = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"


def spawn_context() -> BaseContext:
    """The ``spawn`` context for a process pool, with this process's global start method made one
    that a spawned child can re-apply (``loky`` inside a joblib launcher's job is not)."""
    method = multiprocessing.get_start_method(allow_none=True)
    if method is not None and method not in multiprocessing.get_all_start_methods():  # unset: left so
        multiprocessing.set_start_method("spawn", force=True)
    return multiprocessing.get_context("spawn")


def dataloader_workers(num_workers: int) -> dict[str, Any]:
    """A DataLoader's worker options for ``num_workers`` processes: their start context (None: no
    processes) and their start, which takes this process's budgets (`locretrieval.limits`)."""
    if num_workers == 0:
        return {"num_workers": 0}
    spawn_context()  # a spawn DataLoader's children re-apply the global method too
    return {
        "num_workers": num_workers,
        "multiprocessing_context": multiprocessing.get_context(DATALOADER_START_METHOD),
        "worker_init_fn": functools.partial(_take_budgets, limits.current()),
    }


def _take_budgets(budgets: limits.Limits, worker: int) -> None:
    """A DataLoader worker's start (``worker_init_fn``): its parent's budgets."""
    limits.use(budgets)
