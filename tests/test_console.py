"""The terminal of a command (`locretrieval.console`): log lines above the progress bars, never
inside them; each line once; a library's own console giving way to the root's. (The command's
screen in a pseudo-terminal: tests/test_commands.py.)"""

import contextlib
import io
import logging
import sys
from collections.abc import Iterator

from helpers import collisions
from tqdm import tqdm

from locretrieval.console import console_output


@contextlib.contextmanager
def terminal() -> Iterator[io.StringIO]:
    """One stream standing for a terminal: stdout and stderr both write to it, and the root logger's
    console writes to stdout, as Hydra's does (entered in a test's body: pytest sets its own streams
    again between a fixture and the test)."""
    screen = io.StringIO()
    console = logging.StreamHandler(screen)
    console.setFormatter(logging.Formatter("[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"))
    root = logging.getLogger()
    streams, handlers, level = (sys.stdout, sys.stderr), root.handlers, root.level
    sys.stdout = sys.stderr = screen
    root.handlers = [console]
    root.setLevel(logging.INFO)  # not `root.level =`: setLevel clears the loggers' cached levels
    try:
        yield screen
    finally:
        (sys.stdout, sys.stderr), root.handlers = streams, handlers
        root.setLevel(level)


def test_a_log_line_is_written_above_the_bar_and_the_bar_drawn_again_below():
    log = logging.getLogger("locretrieval.test")
    with terminal() as screen:
        with console_output(), tqdm(total=4, desc="match", file=sys.stderr, mininterval=0, ascii=True) as bar:
            bar.update(1)
            log.info("matching 1487 image pairs")
            bar.update(1)
        written = screen.getvalue()
        with tqdm(total=4, desc="match", file=sys.stderr, mininterval=0, ascii=True) as bar:
            bar.update(1)
            log.info("matching 1487 image pairs")  # without: the line lands inside the bar's
    assert collisions(written) == [] and collisions(screen.getvalue()[len(written) :]) != []
    before, after = written.split("matching 1487 image pairs\n")
    assert "match:  25%" in before and "2/4" in after  # the bar cleared, the line written, the bar drawn again


def test_a_line_said_already_is_not_said_again_in_the_console_or_the_file_but_a_warning_is(tmp_path):
    file = logging.FileHandler(tmp_path / "evaluate.log")
    log = logging.getLogger("locretrieval.sfm.pose_cache")
    with terminal() as screen:
        logging.getLogger().addHandler(file)
        with console_output():
            for _ in range(3):
                log.info("929 registration outcomes read from 13 part(s)")
                log.warning("a warning")
            logging.getLogger("locretrieval.other").info("929 registration outcomes read from 13 part(s)")  # another's
    file.close()
    for text in (screen.getvalue(), (tmp_path / "evaluate.log").read_text()):
        assert text.count("929 registration outcomes read from 13 part(s)") == 2 and text.count("a warning") == 3


def test_a_library_s_own_console_gives_way_to_the_root_s():
    """As `import lightning` sets up ``lightning`` (its own console, ``INFO: ...``, and on to the root)
    and ``lightning.pytorch`` when nothing is set up yet (its own console, nothing passed on)."""
    with terminal() as screen:
        umbrella, package = logging.getLogger("library_test"), logging.getLogger("library_test_pytorch")
        for logger, propagate in ((umbrella, True), (package, False)):
            own = logging.StreamHandler(sys.stderr)
            own.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
            logger.handlers, logger.propagate = [own], propagate
        with console_output():
            logging.getLogger("library_test.utilities.rank_zero").info("`Trainer.fit` stopped")
            logging.getLogger("library_test_pytorch.trainer").info("the package's line")
    text = screen.getvalue()
    assert text.count("`Trainer.fit` stopped") == 1 and text.count("the package's line") == 1
    assert "INFO: " not in text and " - `Trainer.fit` stopped" in text  # the root's console's format
