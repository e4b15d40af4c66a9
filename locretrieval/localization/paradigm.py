"""What every localization paradigm shares: its settings' ``enabled`` switch and ``k`` list."""

from __future__ import annotations

import abc
from dataclasses import dataclass

from locretrieval.config import require


@dataclass
class ParadigmSettings(abc.ABC):
    """A paradigm section of ``configs/paradigms``: whether it runs, and the numbers ``k`` of
    top-ranked database images it uses (each a separate result; a value beyond a ranking's
    depth uses every ranked image and keeps its label, see `locretrieval.benchmark`). Each
    paradigm's subclass says which methods it writes (`method_names`)."""

    enabled: bool
    k: list[int]

    def __post_init__(self) -> None:
        require(len(self.k) > 0, "k", "must list at least one value, e.g. [1, 5, 10]")
        require(min(self.k) >= 1, "k", f"values must be >= 1, got {self.k}")

    @abc.abstractmethod
    def method_names(self) -> list[str]:
        """The ``method`` of every pose estimate the paradigm writes (a column of the results)."""
