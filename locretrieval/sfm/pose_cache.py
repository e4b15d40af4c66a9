"""`PoseCache`: the SfM paradigms' registration outcomes, cached by what produced them.

A query registered from a set of database images (a local map triangulated from them, or
their observations of the global map) gives the same outcome whichever ranking, k or run
selects the set: pycolmap's RANSAC is seeded (``sfm.pnp.random_seed``). One folder per
paradigm source (its map or maps, the query matches' store and the PnP settings, all in the
folder name's key) holds every outcome computed so far, each keyed by the query's name and the
set's database image names; a rerun, another ranking of the same images, or the training
callback's next epoch computes only the sets it has not seen.

Safe for concurrent writers (shards of one evaluation, several runs sharing a cache): each save
writes a new part file holding only that writer's new outcomes, atomically, and readers take the
union of the parts, so no writer's entries are lost. A running paradigm saves every second or so,
so a killed run loses at most that much work. Once a cache knows of `MAX_PARTS` parts (read or
written by itself), a save merges them with its own outcomes into one file and deletes the parts
it merged (never those other writers wrote since it read); a reader that finds a part gone reads
the folder again.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from locretrieval.cache import config_key, load_arrays, save_arrays
from locretrieval.estimates import LOCALIZED

log = logging.getLogger(__name__)

#: Part files a folder may hold before a save merges them.
MAX_PARTS = 32
#: Bytes of an entry's key (a truncated SHA-256 of the query's and the images' names).
KEY_BYTES = 16
#: A query's result for one set of images: world-to-camera (q wxyz, t), or a failure reason.
Outcome = tuple[np.ndarray, np.ndarray] | str


class PoseCache:
    """Outcomes by (query, set of database images) of one paradigm source, stored in the folder
    ``path`` (part files ``.npz``: entry keys as uint8 rows of 16 bytes, ``qvec`` wxyz, ``tvec``,
    failure ``reason``, ``""`` when localised); ``path=None`` caches within this object only."""

    def __init__(self, path: Path | None, query_names: Sequence[str], database_names: Sequence[str]) -> None:
        self.path = path
        self.query_names = query_names
        self.database_names = database_names
        self.outcomes: dict[bytes, Outcome] = {}
        self._new: dict[bytes, Outcome] = {}
        self._parts: list[Path] = []  # the parts read or written, whose entries are all in `outcomes`
        self._saved, self._unreported = time.monotonic(), 0
        if path is not None:
            self._read()

    @property
    def new(self) -> int:
        """Outcomes put since the last save."""
        return len(self._new)

    def _read(self) -> None:
        """Every part of the folder (again from the start when a concurrent merge removed one)."""
        while True:
            parts = sorted(self.path.glob("[!.]*.npz")) if self.path.is_dir() else []
            try:
                arrays = [load_arrays(part) for part in parts]
            except FileNotFoundError:
                continue
            break
        for part in arrays:
            for key, qvec, tvec, reason in zip(part["keys"], part["qvec"], part["tvec"], part["reason"]):
                self.outcomes[key.tobytes()] = (qvec, tvec) if reason == LOCALIZED else str(reason)
        self._parts = parts
        if parts:
            log.info("%d registration outcomes read from %d part(s) in %s", len(self.outcomes), len(parts), self.path)

    def entry(self, query: int, images: Iterable[int]) -> bytes:
        """The key of a query registered from database images ``images`` (indices)."""
        names = sorted(self.database_names[i] for i in images)
        return hashlib.sha256("\n".join([self.query_names[query], *names]).encode()).digest()[:KEY_BYTES]

    def get(self, query: int, images: Iterable[int]) -> Outcome | None:
        return self.outcomes.get(self.entry(query, images))

    def put(self, query: int, images: Iterable[int], outcome: Outcome) -> None:
        key = self.entry(query, images)
        if key not in self.outcomes:
            self.outcomes[key] = self._new[key] = outcome

    def save(self, every: float = 0.0) -> None:
        """Write the outcomes put since the last save as a part of their own (merged with every
        part this object read or wrote, into one, once it knows of `MAX_PARTS`). With ``every``
        (seconds), only when the last save is at least that old, logged only at debug level;
        without, the outcomes saved since the last such call are logged."""
        if self.path is not None and self._new and time.monotonic() - self._saved >= every:
            merge = len(self._parts) >= MAX_PARTS
            written = _write_part(self.path, self.outcomes if merge else self._new)
            if merge:
                for part in self._parts:
                    if part != written:
                        part.unlink(missing_ok=True)
                self._parts = []
            self._parts.append(written)
            self._unreported += len(self._new)
            log.debug("%d registration outcomes saved to %s%s", len(self._new), self.path, " (merged)" * merge)
            self._new, self._saved = {}, time.monotonic()
        if not every and self._unreported:
            log.info("%d new registration outcomes saved to %s", self._unreported, self.path)
            self._unreported = 0


def _write_part(folder: Path, entries: dict[bytes, Outcome]) -> Path:
    """One part file of ``entries``, named by their keys (two writers of the same entries write
    the same file), written atomically."""
    keys = sorted(entries)
    qvec, tvec = np.full((len(keys), 4), np.nan), np.full((len(keys), 3), np.nan)
    reasons = []
    for row, key in enumerate(keys):
        outcome = entries[key]
        if isinstance(outcome, str):
            reasons.append(outcome)
        else:
            qvec[row], tvec[row] = outcome
            reasons.append(LOCALIZED)
    path = folder / f"{config_key(b''.join(keys).hex())}.npz"
    save_arrays(
        path,
        {
            "keys": np.frombuffer(b"".join(keys), np.uint8).reshape(-1, KEY_BYTES),
            "qvec": qvec,
            "tvec": tvec,
            "reason": np.array(reasons, dtype=str),
        },
    )
    return path
