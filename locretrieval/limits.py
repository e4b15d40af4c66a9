"""The ``limits`` config group: budgets of what a file may make the loaders build, and whose classes a
file read as data may name (``trusted_packages``, `locretrieval.parts.resolve_recorded`).

`Limits` is the section's schema (``configs/limits/default.yaml`` holds the defaults and says
what each key bounds). The loaders read the budgets where they run (`current`): the build step sets
those of the run's config once (`use`), and the worker processes the run starts get them with their
start (`locretrieval.pool`, the DataLoaders' `locretrieval.processes.dataloader_workers`); a process
that never set them (a library user, ``report.py``, a test) reads the defaults of the YAML file.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import yaml

from locretrieval.errors import require
from locretrieval.resources import configs_dir

#: The defaults: the config group's one file (in the shipped configs).
DEFAULTS_FILE = ("limits", "default.yaml")
#: Bytes every budget of sizes allows on top of its factor (small files keep working whatever they hold).
SLACK_BYTES = 1 << 20
OUTSIDE_IMAGES = ("allow", "refuse")


@dataclass(frozen=True)
class Limits:
    """The ``limits`` section (``configs/limits/default.yaml`` says what each key bounds)."""

    pickle_depth: int
    pickle_size_factor: int
    compression_ratio: int
    kapture_rows: int
    yaml_nodes: int
    folder_entries: int
    image_pixels: int
    list_file_bytes: int
    outside_images: str
    trusted_packages: list[str]

    def __post_init__(self) -> None:
        counts = ("pickle_depth", "pickle_size_factor", "compression_ratio", "kapture_rows", "yaml_nodes")
        for name in (*counts, "folder_entries", "image_pixels", "list_file_bytes"):
            require(getattr(self, name) >= 1, name, f"must be >= 1, got {getattr(self, name)}")
        require(
            self.outside_images in OUTSIDE_IMAGES,
            "outside_images",
            f"must be one of {list(OUTSIDE_IMAGES)}, got {self.outside_images!r}",
        )
        for package in self.trusted_packages:
            require(
                all(part.isidentifier() for part in str(package).split(".")),
                "trusted_packages",
                f"{package!r} is not a package name (dotted identifiers, e.g. my_package)",
            )

    def size_budget(self, stored_bytes: int, factor: int) -> int:
        """Bytes (or elements) that ``stored_bytes`` of a file may become under ``factor``: ``factor
        x stored_bytes`` + `SLACK_BYTES`."""
        return factor * stored_bytes + SLACK_BYTES


#: The budgets `use` set in this process (None: the defaults).
_in_use: Limits | None = None


def use(checked: Limits | None) -> Limits:
    """Make ``checked`` (the run's ``limits`` section; None: the defaults again) the budgets of this
    process, as `current` reads them; returns them."""
    global _in_use
    _in_use = checked
    return current()


def current() -> Limits:
    """The budgets of this process: those `use` set, else the defaults of `DEFAULTS_FILE`."""
    return _in_use if _in_use is not None else defaults()


@functools.cache
def defaults() -> Limits:
    """The budgets of the defaults file."""
    return Limits(**yaml.safe_load(configs_dir().joinpath(*DEFAULTS_FILE).read_text()))
