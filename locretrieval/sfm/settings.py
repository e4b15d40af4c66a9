"""The ``sfm`` config group (`SfmSettings`): what the SfM paradigms and the co-observation ground truth
share, so that they share their cached features and matches."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from locretrieval.config import part, require
from locretrieval.pool import resolve_workers
from locretrieval.sfm.features import LocalFeatures
from locretrieval.sfm.matching import MatchingSettings
from locretrieval.sfm.pairs import PairSelection
from locretrieval.sfm.pnp import PnPSettings
from locretrieval.sfm.triangulation import Triangulation
from locretrieval.sfm.verification import PairVerification


@dataclass
class SfmSettings:
    """The ``sfm`` config group, shared by local SfM (2a), global SfM (2b) and the
    co-observation ground truth so that they share their cached features and matches:
    local ``features`` (a `LocalFeatures` chosen by ``_target_``), ``matching``, the
    ``query_verification`` of query-database matches and the ``database_verification`` of
    database pairs (each a `PairVerification` chosen by ``_target_``), ``triangulation`` with
    known poses (a `Triangulation` chosen by ``_target_``), ``pnp``
    registration, the database pairs of global maps (``map_pairs``, by frustum overlap) and the
    worker processes (``workers``: ``null`` or 0, one per core; 1, in this process). Which share
    of the work a job does is the job's (`locretrieval.shard.Shard`), not a setting of this group."""

    features: Any = part(LocalFeatures, "sfm/features")
    matching: MatchingSettings
    query_verification: Any = part(PairVerification, "sfm/query_verification")
    database_verification: Any = part(PairVerification, "sfm/database_verification")
    triangulation: Any = part(Triangulation, "sfm/triangulation")
    pnp: PnPSettings
    map_pairs: PairSelection
    workers: int | None

    def __post_init__(self) -> None:
        require(self.workers is None or self.workers >= 0, "workers", f"must be >= 0 or null, got {self.workers}")

    @property
    def processes(self) -> int:
        """Worker processes to use (`resolve_workers`)."""
        return resolve_workers(self.workers)
