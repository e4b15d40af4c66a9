"""The project's errors: a data or cache file that cannot be used, a configuration value refused."""

from __future__ import annotations

import os

#: What to do about a damaged cache file (caches are keyed by what produced them: deleting one recomputes it).
DELETE_CACHE_FILE = "delete it: it is recomputed on the next run"
#: What to do about a damaged data file (a dataset, weight or ground-truth file).
FIX_DATA_FILE = "fix or replace the file (e.g. download it again)"


class DataFileError(ValueError):
    """A file the run reads (dataset, weights, ground truth, cache, run table) that cannot be used.

    The message starts with the file's path, says what is wrong and what to do (`DELETE_CACHE_FILE`
    for caches, `FIX_DATA_FILE` for inputs); ``path`` is the file."""

    def __init__(self, path: str | os.PathLike, problem: str, remedy: str | None = None) -> None:
        self.path = str(path)
        super().__init__(f"{path}: {problem}" + (f"; {remedy}" if remedy else ""))


class ConfigError(ValueError):
    """A configuration value of the wrong type or range; the message names the full key."""


class SettingError(ValueError):
    """A value a schema's ``__post_init__`` refuses; ``field`` is its key within the schema."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")


def require(condition: bool, field: str, message: str) -> None:
    """Raise `SettingError` for ``field`` unless ``condition`` (a range check of a schema)."""
    if not condition:
        raise SettingError(field, message)


def require_built(run: object, kind: type, builder: str) -> None:
    """Refuse anything but a ``kind`` run object where an entry function expects one: since 0.12 the
    entry functions take what `locretrieval.build` made of a composed config, not the config."""
    if not isinstance(run, kind):
        raise TypeError(
            f"a {kind.__name__} is expected, not a {type(run).__name__}: build it from the composed config "
            f"first, locretrieval.build.{builder}(cfg)"
        )
