"""Thread counts of the threaded numeric libraries, fixed where a result would follow them.

A threaded matrix product or reduction splits its sums by the number of threads, so its last bits
(and through a k-means or a top-k, whole results) depend on the machine's core count and on the
limits a launcher sets (Hydra's joblib launcher gives each job ``cores / n_jobs`` BLAS threads).
Steps whose output is cached or compared are therefore run on fixed single-threaded units:
`single_threaded` around a library call, or `map_single_threaded` over fixed chunks of the work
in parallel threads (each chunk's arithmetic is the same whatever the thread count).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import threadpoolctl

Item = TypeVar("Item")
Result = TypeVar("Result")


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """torch's intra-op threads set to ``count`` (its BLAS included), restored afterwards."""
    import torch  # here: the SfM workers, which use this module, do not need torch

    previous = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


#: Blocks of `single_threaded` open in this process, and what closing the last one restores.
_single = {"depth": 0, "restore": None}
_single_lock = threading.Lock()


@contextlib.contextmanager
def single_threaded() -> Iterator[None]:
    """Every BLAS (numpy's and faiss's OpenBLAS, torch's MKL), OpenMP runtime and torch on one
    thread within the block, for this thread (an OpenMP limit holds per thread) and for the
    libraries' process-wide settings (BLAS, torch: other Python threads are affected too). Blocks
    may overlap in several threads: the first sets the limits, the last restores them."""
    import torch

    with _single_lock:
        if _single["depth"] == 0:
            threads = torch.get_num_threads()  # before the limits: torch's count follows its OpenMP limit
            _single["restore"] = (threadpoolctl.threadpool_limits(1), threads)
            torch.set_num_threads(1)
        else:
            threadpoolctl.threadpool_limits(1)  # this thread's own OpenMP limit
        _single["depth"] += 1
    try:
        yield
    finally:
        with _single_lock:
            _single["depth"] -= 1
            if _single["depth"] == 0:
                limits, threads = _single["restore"]
                limits.restore_original_limits()
                torch.set_num_threads(threads)


def _single_threaded_worker() -> None:
    """A `map_single_threaded` thread's own OpenMP limit (per thread: a new thread starts with
    ``OMP_NUM_THREADS``, and faiss's OpenBLAS follows it); it ends with the thread."""
    threadpoolctl.threadpool_limits(1)


def map_single_threaded(function: Callable[[Item], Result], items: Iterable[Item]) -> list[Result]:
    """``function(item)`` for each item, in order, in parallel Python threads (as many as torch's
    thread count, which follows ``OMP_NUM_THREADS`` and a launcher's limits), with every library
    single-threaded: as fast as a threaded library on independent chunks, and each
    result independent of the thread count. ``function`` should release the GIL (torch, numpy
    and faiss kernels do)."""
    import torch

    items, workers = list(items), torch.get_num_threads()
    with (
        single_threaded(),
        ThreadPoolExecutor(max(1, min(len(items), workers)), initializer=_single_threaded_worker) as pool,
    ):
        return list(pool.map(function, items))
