"""A report's figures drawn in worker processes.

matplotlib draws on one core and a report's figures are independent, so `Painters.draw` hands
each plotting call to a pool of workers (one per core, started on first use and kept
for the process) and returns a future of the files it writes; `ReportWriter.write` waits for
them. Workers import matplotlib, pandas and the plotting module only (about a second).
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import Any

from locretrieval.pool import WorkerPool, resolve_workers
from locretrieval.report.plots import FigureFolder, pyplot


class Painters:
    """Runs ``plot(*args, **kwargs)`` calls that write figures into ``figures``: in ``workers``
    processes (``None`` or 0: one per core; 1: in this process). Without a figure format nothing
    is drawn (``report.figure_formats=[]``) and matplotlib is not imported."""

    def __init__(self, figures: FigureFolder, workers: int | None = None) -> None:
        self.figures = figures
        self.workers = resolve_workers(workers)
        if self.figures.formats:
            start_painters(self.workers)  # they import while the tables load

    def draw(self, plot: Callable[..., list[Path]], *args: Any, **kwargs: Any) -> Future:
        """A future of the files ``plot`` writes (a module-level function; arguments picklable)."""
        if not self.figures.formats or self.workers == 1:
            done: Future = Future()
            done.set_result(plot(*args, **kwargs) if self.figures.formats else [])
            return done
        return _painters.submit(self.workers, plot, *args, **kwargs)


def start_painters(workers: int | None = None) -> None:
    """Start the figure workers now (``workers`` as in `Painters`), e.g. while a run computes
    what its report will draw: each spends about a second importing matplotlib."""
    _painters.start(resolve_workers(workers))


#: The figure workers of this process: each imports matplotlib's pyplot as it starts.
_painters = WorkerPool("figures", initializer=pyplot)
