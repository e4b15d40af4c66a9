"""`Shard`: this job's share of one evaluation's SfM work (``evaluate.yaml``'s ``shard``, or a DDP rank's).

A property of the job, not an SfM setting: ``python evaluate.py -m 'shard=0/4,1/4,2/4,3/4'`` runs
four jobs sharing the cache, each computing every 4th item of each stage's sorted work
(`locretrieval.paradigms.sfm`); the same command without ``shard`` then writes the results.
The value is parsed once, where the job starts (`Shard.parse`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from locretrieval.config import ConfigError


@dataclass(frozen=True)
class Shard:
    """The ``index``-th of ``count`` jobs sharing one evaluation's SfM work: every list of work
    items, sorted, is split by taking every ``count``-th from ``index``."""

    index: int
    count: int

    def __post_init__(self) -> None:
        if not 0 <= self.index < self.count:
            raise ValueError(f"shard {self.index}/{self.count}: needs 0 <= index < count")

    @classmethod
    def parse(cls, value: Any, key: str) -> Shard | None:
        """The shard of the config value ``value`` at ``key`` (``"i/n"``), or None for null (the
        whole work); anything else is a `ConfigError` naming ``key``."""
        if value is None:
            return None
        parts = str(value).split("/")
        if len(parts) == 2 and all(part.strip().isdigit() for part in parts):
            index, count = int(parts[0]), int(parts[1])
            if 0 <= index < count:
                return cls(index, count)
        raise ConfigError(
            f"{key}: must be 'i/n' with 0 <= i < n (this job's share of the SfM work), or null, got {value!r}"
        )

    def take(self, items: Sequence[Any]) -> list[Any]:
        """This shard's items of ``items`` (in a deterministic order)."""
        return list(items[self.index :: self.count])

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"
