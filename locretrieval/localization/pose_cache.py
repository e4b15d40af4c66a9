"""`PoseCache`: the SfM paradigms' registration outcomes, cached by what produced them.

A query registered from a set of database images (a local map triangulated from them, or
their observations of the global map) gives the same outcome whichever ranking, k or run
selects the set: pycolmap's RANSAC is seeded (``sfm.pnp.random_seed``). One file per
paradigm source (its map or maps, the query matches' store and the PnP settings, all in the
file name's key) holds every outcome computed so far, each keyed by the query's name and the
set's database image names; a rerun, another ranking of the same images, or the training
callback's next epoch computes only the sets it has not seen.

Concurrent runs sharing a cache folder each rewrite the file atomically with what they read
and computed: the last writer wins, so a concurrent run's new outcomes may be missing from the
file later (computed again, never wrong).
"""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from locretrieval.cache import load_arrays, save_arrays
from locretrieval.localization.estimates import LOCALIZED

log = logging.getLogger(__name__)

#: Bytes of an entry's key (a truncated SHA-256 of the query's and the images' names).
KEY_BYTES = 16
#: A query's result for one set of images: world-to-camera (q wxyz, t), or a failure reason.
Outcome = tuple[np.ndarray, np.ndarray] | str


class PoseCache:
    """Outcomes by (query, set of database images) of one paradigm source, stored at ``path``
    (``.npz``: entry keys as uint8 rows of 16 bytes, ``qvec`` wxyz, ``tvec``, failure ``reason``, ``""`` when
    localised); ``path=None`` caches within this object only."""

    def __init__(self, path: Path | None, query_names: Sequence[str], database_names: Sequence[str]) -> None:
        self.path = path
        self.query_names = query_names
        self.database_names = database_names
        self.outcomes: dict[bytes, Outcome] = {}
        self.new = 0
        if path is not None and path.is_file():
            arrays = load_arrays(path)
            for key, qvec, tvec, reason in zip(arrays["keys"], arrays["qvec"], arrays["tvec"], arrays["reason"]):
                self.outcomes[key.tobytes()] = (qvec, tvec) if reason == LOCALIZED else str(reason)
            log.info("%d registration outcomes read from %s", len(self.outcomes), path)

    def entry(self, query: int, images: Iterable[int]) -> bytes:
        """The key of a query registered from database images ``images`` (indices)."""
        names = sorted(self.database_names[i] for i in images)
        return hashlib.sha256("\n".join([self.query_names[query], *names]).encode()).digest()[:KEY_BYTES]

    def get(self, query: int, images: Iterable[int]) -> Outcome | None:
        return self.outcomes.get(self.entry(query, images))

    def put(self, query: int, images: Iterable[int], outcome: Outcome) -> None:
        key = self.entry(query, images)
        if key not in self.outcomes:
            self.outcomes[key] = outcome
            self.new += 1

    def save(self) -> None:
        """Write every outcome (read and new) when some are new."""
        if self.path is None or not self.new:
            return
        keys = list(self.outcomes)
        qvec, tvec = np.full((len(keys), 4), np.nan), np.full((len(keys), 3), np.nan)
        reasons = []
        for row, key in enumerate(keys):
            outcome = self.outcomes[key]
            if isinstance(outcome, str):
                reasons.append(outcome)
            else:
                qvec[row], tvec[row] = outcome
                reasons.append(LOCALIZED)
        save_arrays(self.path, {
            "keys": np.frombuffer(b"".join(keys), np.uint8).reshape(-1, KEY_BYTES),
            "qvec": qvec, "tvec": tvec, "reason": np.array(reasons, dtype=str),
        })
        log.info("%d new registration outcomes (%d in all) saved to %s", self.new, len(keys), self.path)
        self.new = 0
