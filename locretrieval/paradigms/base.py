"""A localization paradigm: one class, built from its section of ``configs/paradigms`` by ``_target_``.

`Paradigm` is the class every paradigm subclasses: its dataclass fields are its settings (the
keys of its YAML, ``configs/paradigms/<name>.yaml``), `Paradigm.run` computes its pose estimates,
and it says what it needs (`Paradigm.missing_inputs`, `Paradigm.uses_sfm`) and what map it built
(`Paradigm.map_points`). An SfM paradigm subclasses `locretrieval.paradigms.sfm.SfmParadigm`, which
says which pairs, maps and registrations it needs. `Paradigms` is the ``paradigms`` config group: the
set and order of the paradigms are its sections', so a new paradigm is one class (in any package)
and one section (``+paradigms.mine={_target_: my.module.Mine, enabled: true, k: [1, 5]}``).
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from locretrieval.config import ConfigError, require, validated
from locretrieval.estimates import PoseEstimates
from locretrieval.retrieval import Ranking
from locretrieval.scene import Scene
from locretrieval.sfm.settings import SfmSettings


@dataclass
class Paradigm(abc.ABC):
    """A paradigm section of ``configs/paradigms``: whether it runs, and the numbers ``k`` of
    top-ranked database images it uses (each a separate result; a value beyond a ranking's depth
    uses every ranked image and keeps its label, see `locretrieval.benchmark`). A subclass adds
    its own settings as fields (checked by `locretrieval.config.validated`), says which methods
    it writes (`method_names`) and computes them (`run`). ``uses_sfm``: whether it reads the ``sfm``
    group's local features and matches (a `locretrieval.paradigms.sfm.SfmParadigm`; its validation
    in training then runs every ``sfm_every_n_epochs`` only)."""

    enabled: bool
    k: list[int]
    uses_sfm: ClassVar[bool] = False

    def __post_init__(self) -> None:
        require(len(self.k) > 0, "k", "must list at least one value, e.g. [1, 5, 10]")
        require(min(self.k) >= 1, "k", f"values must be >= 1, got {self.k}")

    @abc.abstractmethod
    def method_names(self) -> list[str]:
        """The ``method`` of every pose estimate the paradigm writes (a column of the results)."""

    @abc.abstractmethod
    def run(
        self, scene: Scene, rankings: Sequence[Ranking], sfm: SfmSettings, cache_dir: Path | None
    ) -> list[PoseEstimates] | None:
        """The pose of every query for every ranking, method and ``k`` (``sfm``: the ``sfm``
        group's settings, ``cache_dir``: where it may reuse what it computed; None only for a job
        of a shard, whose share is cached)."""

    def missing_inputs(self) -> list[str]:
        """The files it reads that are absent, each ``<key>: <problem>`` (default: none)."""
        return []

    def map_points(self, scene: Scene, sfm: SfmSettings, cache_dir: Path) -> np.ndarray | None:
        """The 3D points ``[P, 3]`` (world, metres) of a map it built, for the report's 3D view,
        or None (default; nothing is computed here)."""
        return None


@dataclass
class Paradigms:
    """The ``paradigms`` config group: one `Paradigm` per section, built by its ``_target_`` and
    checked by its class (`locretrieval.config.validated`), in the config's order; read as an
    attribute of its name (``settings.paradigms.local_sfm``)."""

    sections: dict[str, Paradigm]

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any], key: str) -> "Paradigms":
        """Each section of ``mapping`` built as the `Paradigm` its ``_target_`` names; a section
        without one, or naming something else, is a `ConfigError` naming its key."""
        if "_target_" in mapping:  # e.g. paradigms=local_sfm: one paradigm's YAML as the whole group
            raise ConfigError(
                f"{key}: one paradigm's YAML in place of the group; the group lists its paradigms "
                f"(configs/paradigms/default.yaml), e.g. {key}.local_sfm.enabled=false switches one off"
            )
        return cls({name: paradigm_of(section, f"{key}.{name}", list(mapping)) for name, section in mapping.items()})

    def __getattr__(self, name: str) -> Paradigm:
        sections = self.__dict__.get("sections", {})
        if name in sections:
            return sections[name]
        raise AttributeError(f"no paradigm section {name!r}; known: {list(sections)}")

    def enabled(self) -> list[str]:
        """The enabled paradigms, in the config's order."""
        return [name for name, section in self.sections.items() if section.enabled]

    def ks(self) -> list[int]:
        """Every k of an enabled paradigm, sorted."""
        return sorted({k for name in self.enabled() for k in self.sections[name].k})

    def sfm_paradigms(self) -> dict[str, Paradigm]:
        """The enabled SfM paradigms (`Paradigm.uses_sfm`), by name, which the benchmark runs together
        (`locretrieval.paradigms.sfm.run_sfm`)."""
        return {name: self.sections[name] for name in self.enabled() if self.sections[name].uses_sfm}

    def only(self, keep: Callable[[Paradigm], bool]) -> "Paradigms":
        """These paradigms with those ``keep`` refuses switched off."""
        return Paradigms(
            {
                name: section if keep(section) else dataclasses.replace(section, enabled=False)
                for name, section in self.sections.items()
            }
        )


def paradigm_of(section: Any, key: str, sections: Sequence[str]) -> Paradigm:
    """The `Paradigm` of the config section ``section`` at ``key`` (one of ``sections``): its
    ``_target_`` class, its other keys checked as that class's fields."""
    from locretrieval.parts import PartGroup, import_part

    if not isinstance(section, Mapping) or "_target_" not in section:
        raise ConfigError(
            f"{key}: a paradigm section without _target_ (its Paradigm class, as in "
            f"configs/paradigms/approximation.yaml); the sections are {list(sections)}"
        )
    target = import_part(section["_target_"], key, PartGroup((Paradigm,)))
    if not (isinstance(target, type) and issubclass(target, Paradigm)) or getattr(target, "__abstractmethods__", ()):
        raise ConfigError(f"{key}._target_: {section['_target_']} is not a Paradigm class")
    return validated(target, {name: value for name, value in section.items() if name != "_target_"}, key)
