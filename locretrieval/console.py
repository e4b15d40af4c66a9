"""The terminal of a command: log lines written above the progress bars, never inside them, each once.

tqdm draws its bars on stderr and rewrites them in place; a log line written to stdout meanwhile
lands inside a bar's line. Within `console_output` the console handlers of the root logger (Hydra's
``console``, report's ``basicConfig``) write through `tqdm.write` (tqdm's `logging_redirect_tqdm`:
the bars are cleared, the line written, the bars drawn again below it), Python's warnings are
logged (`logging.captureWarnings`) instead of being written between two redraws of a bar, a
line said already is not said again (`SaidOnce`: several stages read the same cache and say so),
and a library's own console (Lightning's) gives way to the root's (`one_console`).
"""

from __future__ import annotations

import contextlib
import logging
import sys
from collections.abc import Iterator

from tqdm.contrib.logging import logging_redirect_tqdm


class SaidOnce(logging.Filter):
    """Lets an informational record (below a warning) through once per text and logger: a stage
    that reads what an earlier one read (a cache, a map) says the same line again. Warnings and
    errors always pass."""

    def __init__(self) -> None:
        super().__init__()
        self._said: set[tuple[str, str]] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING:
            return True
        said = (record.name, record.getMessage())
        if said in self._said:
            return False
        self._said.add(said)
        return True


def one_console() -> None:
    """Hand the records of the loggers below the root that have a console of their own to the
    root's (``import lightning`` gives the ``lightning`` logger one, ``INFO: ...``, which writes
    the line a second time, inside a bar; ``lightning.pytorch``, imported before any logging is
    set up, writes to its own and passes nothing on): each line written once, above the bars.
    Call it after importing such a library."""
    terminal = (sys.stdout, sys.stderr)
    for logger in logging.Logger.manager.loggerDict.values():
        if not isinstance(logger, logging.Logger):
            continue
        consoles = [h for h in logger.handlers if isinstance(h, logging.StreamHandler) and h.stream in terminal]
        if consoles:
            logger.handlers = [handler for handler in logger.handlers if handler not in consoles]
            logger.propagate = True


@contextlib.contextmanager
def console_output() -> Iterator[None]:
    """Log lines and warnings above the progress bars, each once, while inside (module docstring)."""
    logging.captureWarnings(True)
    one_console()
    try:
        with logging_redirect_tqdm():
            filters = [(handler, SaidOnce()) for handler in logging.getLogger().handlers]  # each handler its own
            for handler, said_once in filters:
                handler.addFilter(said_once)
            try:
                yield
            finally:
                for handler, said_once in filters:
                    handler.removeFilter(said_once)
    finally:
        logging.captureWarnings(False)
