"""Which images of a reconstruction are queries, the others being the database (``data.split``,
chosen by its ``_target_``: ``configs/data/split/``).

A split sees the registered images' names (paths relative to the image folder, ``/``-separated,
sorted) and returns a boolean mask of the queries. Every split must leave at least one query and
one database image.
"""

from __future__ import annotations

import abc
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from locretrieval import limits
from locretrieval.config import require
from locretrieval.errors import FIX_DATA_FILE, DataFileError

log = logging.getLogger(__name__)


class SceneSplit(abc.ABC):
    """Chooses the queries among the registered images (a new one subclasses this, in any package)."""

    @abc.abstractmethod
    def queries(self, names: Sequence[str]) -> np.ndarray:
        """Boolean ``[len(names)]``: the images that are queries."""

    def check(self, registered: Sequence[str], images: Sequence[str]) -> None:
        """Raise for a split that names what is not there (``images``: every image of the folder;
        ``registered``: those of the scene); nothing to check by default."""

    def split(self, registered: Sequence[str], images: Sequence[str]) -> np.ndarray:
        """`queries` of the ``registered`` names (`check` first), checked to leave at least one
        query and one database image."""
        self.check(registered, images)
        names = registered
        mask = np.asarray(self.queries(names), dtype=bool)
        if mask.shape != (len(names),):
            raise ValueError(f"data.split: {type(self).__name__} returned {mask.shape} flags for {len(names)} images")
        if not mask.any() or mask.all():
            role = "query" if not mask.any() else "database image"
            raise ValueError(
                f"data.split ({self!r}) leaves no {role} among the {len(names)} registered images "
                f"(e.g. {list(names[:3])}); choose another split (configs/data/split/)"
            )
        return mask


@dataclass(frozen=True)
class EveryNth(SceneSplit):
    """Every ``step``-th registered image in name order, from the ``offset``-th (0-based), is a query."""

    step: int
    offset: int

    def __post_init__(self) -> None:
        require(self.step >= 2, "step", f"must be >= 2 (1 would leave no database image), got {self.step}")
        require(0 <= self.offset < self.step, "offset", f"must be in [0, step), got {self.offset}")

    def queries(self, names: Sequence[str]) -> np.ndarray:
        return np.arange(len(names)) % self.step == self.offset


@dataclass(frozen=True)
class NamePattern(SceneSplit):
    """Images whose name matches the regular expression ``pattern`` (``re.search``) are queries."""

    pattern: str

    def __post_init__(self) -> None:
        try:
            re.compile(self.pattern)
        except re.error as error:
            raise ValueError(f"data.split.pattern: invalid regular expression {self.pattern!r}: {error}") from None

    def queries(self, names: Sequence[str]) -> np.ndarray:
        regex = re.compile(self.pattern)
        return np.array([bool(regex.search(name)) for name in names], dtype=bool)


@dataclass(frozen=True)
class HeldOutSequences(SceneSplit):
    """The images of the ``sequences`` held out are queries; an image's sequence is its folder within
    the image folder (``seq2/000123.jpg`` is in ``seq2``; an image at the top is in ``""``)."""

    sequences: list[str]

    def __post_init__(self) -> None:
        require(bool(self.sequences), "sequences", "must name at least one sequence (a folder of the images)")

    def check(self, registered: Sequence[str], images: Sequence[str]) -> None:
        folders = {sequence_of(name) for name in images}
        unknown = sorted(set(self.sequences) - folders)
        if unknown:
            raise ValueError(
                f"data.split.sequences: {unknown} are no folders of the images; they are {sorted(folders)}"
            )

    def queries(self, names: Sequence[str]) -> np.ndarray:
        held_out = set(self.sequences)
        return np.array([sequence_of(name) in held_out for name in names], dtype=bool)


def sequence_of(name: str) -> str:
    """The sequence of an image: its folder within the image folder (``""`` at the top)."""
    return name.rpartition("/")[0]


@dataclass(frozen=True)
class ListFile(SceneSplit):
    """The images named in the text file ``path`` (one name per line, relative to the image folder;
    blank lines and ``#`` comments ignored) are queries. A listed image that is not registered is
    left out with a warning (in the log of the loader); a name that is no image of the folder is an
    error naming its line."""

    path: str

    def listed(self) -> list[tuple[int, str]]:
        """``(line number, name)`` of each name the file lists (at most ``limits.list_file_bytes``)."""
        path = Path(self.path)
        if not path.is_file():
            raise FileNotFoundError(f"data.split.path: query list file {path} not found")
        most = limits.current().list_file_bytes
        if path.stat().st_size > most:
            raise DataFileError(
                path,
                f"{path.stat().st_size} bytes, more than {most} (limits.list_file_bytes; refused before reading it): "
                "a list of image names is far smaller; raise the limit for a longer list",
            )
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as error:
            raise DataFileError(path, f"not UTF-8 text ({error.reason})", FIX_DATA_FILE) from None
        lines = [(number, line.strip()) for number, line in enumerate(text.splitlines(), start=1)]
        return [(number, name) for number, name in lines if name and not name.startswith("#")]

    def queries(self, names: Sequence[str]) -> np.ndarray:
        listed = {name for _, name in self.listed()}
        return np.array([name in listed for name in names], dtype=bool)

    def check(self, registered: Sequence[str], images: Sequence[str]) -> None:
        """Raise for a listed name that is no image of the folder; warn about listed images that are not registered."""
        known = set(images)
        listed = self.listed()
        for number, name in listed:
            if name not in known:
                raise DataFileError(
                    f"{self.path}:{number}",
                    f"{name[:200]!r} is not an image of the image folder (names are relative to data.images)",
                )
        unregistered = sorted({name for _, name in listed} - set(registered))
        if unregistered:
            log.warning(
                "%d of the queries listed in %s are not registered and left out, e.g. %s",
                len(unregistered),
                self.path,
                unregistered[:3],
            )
