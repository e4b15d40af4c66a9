"""Folders walked without a link leading the walk astray, and folders written without a write
following a link out of them.

- `walk`: the entries below a folder, each folder's in name order before those of its subfolders
  (`FolderEntry`: its name relative to the folder, whether it is a folder, where a symbolic link
  resolves and whether that is outside the folder). A link to a folder inside is not followed
  (what it leads to is walked where it is); one leading outside is followed only when asked, and
  a folder reached twice (``a -> .``, ``root -> /`` and its own loops) is walked once. At most
  ``limits.folder_entries`` entries are listed (a `DataFileError` naming the folder past them): a
  walk ends, and in bounded memory.
- `check_written_folder`: a folder a run, an export or a sweep writes into holds no link that
  resolves outside it (a `DataFileError` naming the first). A folder given to write may be an old
  one someone else prepared (a shared sweep resumed, an export into an existing folder); a link
  planted there (``config.yaml -> ~/.bashrc``, ``hloc -> /elsewhere``, ``optuna.db -> ...``) would
  make a write land outside. `PlantedLinks` checks the run's or sweep's folder before Hydra writes
  its first file there (``hydra.callbacks.planted_links`` of every entry point's config).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

from locretrieval import limits
from locretrieval.errors import DataFileError


def inside(path: str | os.PathLike, folder: str | os.PathLike) -> bool:
    """Whether ``path`` resolves (symbolic links followed) inside ``folder`` (resolved too)."""
    resolved, root = os.path.realpath(path), os.path.realpath(folder)
    return os.path.commonpath([resolved, root]) == root


@dataclass(frozen=True)
class FolderEntry:
    """A file or folder found by `walk`: ``name`` (``/``-separated, relative to the folder walked),
    ``path`` (as reached, through the links followed), ``is_dir`` (links followed), and for a
    symbolic link its resolved ``target`` and whether that lies ``outside`` the folder walked."""

    name: str
    path: str
    is_dir: bool
    target: str | None = None
    outside: bool = False


def walk(folder: str | os.PathLike, hidden: bool, follow_outside: bool) -> Iterator[FolderEntry]:
    """Every file and folder below ``folder`` (module docstring), ``hidden`` ones (a name starting
    with ``.``) included or skipped with what they hold; links to folders outside it are walked
    when ``follow_outside``. The consumer may stop at an entry before what it holds is walked."""
    most = limits.current().folder_entries
    root = os.path.realpath(folder)
    seen = {_identity(folder)}
    pending: list[tuple[str, str]] = [(os.fspath(folder), "")]
    listed = 0
    while pending:
        directory, prefix = pending.pop()
        try:
            with os.scandir(directory) as scan:
                entries = sorted(scan, key=lambda entry: entry.name)
        except OSError as error:
            raise DataFileError(directory, f"cannot list this folder ({error.strerror})") from None
        below = []
        for entry in entries:
            if not hidden and entry.name.startswith("."):
                continue
            listed += 1
            if listed > most:
                raise DataFileError(
                    folder,
                    f"more than {most} files and folders below it (limits.folder_entries; links to folders "
                    "outside it are walked too): raise it for a larger folder",
                )
            found = _entry(entry, prefix, root)
            yield found
            if found.is_dir and (found.target is None or (found.outside and follow_outside)):
                try:
                    identity = _identity(entry.path)
                except OSError as error:
                    raise DataFileError(entry.path, f"cannot list this folder ({error.strerror})") from None
                if identity not in seen:
                    seen.add(identity)
                    below.append((entry.path, f"{found.name}/"))
        pending.extend(reversed(below))


def _entry(entry: os.DirEntry, prefix: str, root: str) -> FolderEntry:
    is_dir = _is_dir(entry)
    if not entry.is_symlink():
        return FolderEntry(prefix + entry.name, entry.path, is_dir)
    try:
        target = os.path.realpath(entry.path)
    except OSError as error:
        raise DataFileError(entry.path, f"a symbolic link that cannot be read ({error.strerror})") from None
    return FolderEntry(prefix + entry.name, entry.path, is_dir, target, not inside(target, root))


def _is_dir(entry: os.DirEntry) -> bool:
    """Whether ``entry`` is a folder (through a link); a link to nowhere or into a loop is not."""
    try:
        return entry.is_dir()
    except OSError:
        return False


def _identity(path: str | os.PathLike) -> tuple[int, int]:
    """``(device, inode)`` of the folder ``path`` leads to: the same folder however it is reached."""
    status = os.stat(path)
    return status.st_dev, status.st_ino


def check_written_folder(folder: str | os.PathLike, role: str) -> None:
    """Raise a `DataFileError` naming the first symbolic link below ``folder`` (the ``role`` it
    plays, for the message: ``run folder (hydra.run.dir)``) that resolves outside it; nothing to
    check where the folder does not exist yet. Links that stay inside it are left alone."""
    if not os.path.isdir(folder):
        return
    for entry in walk(folder, hidden=True, follow_outside=False):
        if entry.outside:
            raise DataFileError(
                entry.path,
                f"a symbolic link to {entry.target}, outside the {role} {folder}; files are written only inside "
                "the folder, never through a link out of it: remove the link or choose another folder",
            )


class PlantedLinks(Callback):
    """Hydra callback (``hydra.callbacks.planted_links``): `check_written_folder` of the run's folder
    (``hydra.run.dir``) or the sweep's (``hydra.sweep.dir``, its jobs' folders inside) before Hydra
    writes there; a link out of it ends the command as a mistake (one screen, exit status 1)."""

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        _check_before_hydra(config.hydra.run.dir, "run folder (hydra.run.dir)")

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        _check_before_hydra(config.hydra.sweep.dir, "sweep folder (hydra.sweep.dir)")


def _check_before_hydra(folder: str, role: str) -> None:
    from locretrieval.cli import reported_mistakes

    with reported_mistakes():
        check_written_folder(Path(folder), role)
