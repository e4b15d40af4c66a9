"""On-disk caches keyed by what produced them, written atomically."""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import os
import re
import shutil
import socket
import struct
import tempfile
import zipfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from locretrieval.bounded_files import check_npz
from locretrieval.errors import DELETE_CACHE_FILE, DataFileError


def config_key(*parts: Any) -> str:
    """Stable 16-hex-digit hash of JSON-serialisable parts (dict keys sorted)."""
    text = json.dumps(parts, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


#: The temporary file of a write in progress: ``.<name>.<host>-<pid>-<random>.partial<suffix>``.
_TEMPORARY = re.compile(r"^\..*\.(?P<host>[^.]+)-(?P<pid>\d+)-[^.]+\.partial[^/]*$")
#: Folders whose killed runs' temporary files this process has removed.
_swept: set[Path] = set()


#: A name usable as one file name as it is: letters, digits, ``._-``, not starting with a dot.
_SAFE_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,99}")


def safe_name(text: str) -> str:
    """``text`` as one file name inside its folder (a ranking, ground-truth, model or figure name):
    unchanged when it is one already (`_SAFE_NAME`); otherwise other characters become ``_`` (a
    leading dot too: no ``..``, no hidden file), cut to 80 characters, followed by ``-`` and 8 hex
    digits of its hash, so that two names never share a file."""
    text = str(text)
    if _SAFE_NAME.fullmatch(text):
        return text
    readable = re.sub(r"[^A-Za-z0-9._-]", "_", text)[:80]
    return re.sub(r"^\.", "_", readable) + "-" + config_key(text)[:8]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success flush it to disk (fsync), move it into
    place and fsync the folder, so a crash or power loss leaves the old file or the new one, never
    a partial one. The first write of this process into a folder removes the temporary files
    that killed processes of this host left there (readers ignore them: they are hidden)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(path.parent)
        handle, temporary = tempfile.mkstemp(
            dir=path.parent, prefix=f".{path.name}.{_HOST}-{os.getpid()}-", suffix=f".partial{path.suffix}"
        )
    except OSError as error:
        raise OSError(
            error.errno,
            f"cannot write {path} ({error.strerror}); is the cache folder writable? "
            "(paths.cache_dir or $LOCRETRIEVAL_CACHE)",
        ) from None
    os.close(handle)
    try:
        yield Path(temporary)
        _fsync(temporary)
        os.replace(temporary, path)
        _fsync(path.parent)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)


_HOST = re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname()) or "host"


def _fsync(path: str | os.PathLike) -> None:
    """Flush a file's (or a folder's entries') data to the disk."""
    handle = os.open(path, os.O_RDONLY)
    try:
        os.fsync(handle)
    finally:
        os.close(handle)


@contextlib.contextmanager
def temporary_folder(parent: str | os.PathLike, label: str) -> Iterator[Path]:
    """A hidden folder of ``parent`` for scratch work, deleted afterwards with the folders made for
    it (or, when this process is killed, by the next process of this host that writes into
    ``parent``)."""
    parent = Path(parent)
    missing = [folder for folder in (parent, *parent.parents) if not folder.exists()]
    parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(parent)
    folder = Path(tempfile.mkdtemp(dir=parent, prefix=f".{label}.{_HOST}-{os.getpid()}-", suffix=".partial"))
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)
        for created in missing:  # the folders made for it, innermost first, unless something else was written there
            with contextlib.suppress(OSError):
                created.rmdir()


def remove_stale_temporaries(folder: Path) -> list[Path]:
    """Delete the `atomic_path` temporary files and `temporary_folder` folders in ``folder``
    whose process (on this host) is gone, once per folder and process; returns those deleted."""
    folder = Path(folder).resolve()
    if folder in _swept:
        return []
    _swept.add(folder)
    removed = []
    with os.scandir(folder) as entries:
        for entry in entries:
            match = _TEMPORARY.match(entry.name) if entry.name.startswith(".") else None
            if match and match["host"] == _HOST and not process_alive(int(match["pid"])):
                if entry.is_dir(follow_symlinks=False):
                    shutil.rmtree(entry.path, ignore_errors=True)
                else:
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(entry.path)
                removed.append(Path(entry.path))
    return removed


def process_alive(pid: int) -> bool:
    """Whether a process ``pid`` runs on this host."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def save_arrays(path: str | os.PathLike, arrays: Mapping[str, np.ndarray]) -> None:
    """Write named arrays to an ``.npz`` file atomically (uncompressed, so loads are fast)."""
    with atomic_path(path) as temporary:
        with open(temporary, "wb") as stream:
            np.savez(stream, **arrays)


def load_arrays(
    path: str | os.PathLike, remedy: str = DELETE_CACHE_FILE, memory_map: bool = False
) -> dict[str, np.ndarray]:
    """Read every array of an ``.npz`` file into memory (no pickled object), or with ``memory_map``
    map each read-only (`save_arrays`'s uncompressed members: only the pages a reader touches are
    read, and processes share them). A file that is not a whole ``.npz`` (truncated, empty, damaged)
    is a `DataFileError` naming it and ``remedy`` (what to do: by default, delete the cache file); a
    missing one a ``FileNotFoundError``."""
    try:
        check_npz(path, remedy)  # every member within limits.compression_ratio, as its header declares
        if memory_map:
            return _mapped_members(path, remedy)
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files}
    except (FileNotFoundError, DataFileError):
        raise
    except Exception as error:  # zipfile and numpy raise a dozen types on a damaged file: all mean "unreadable"
        raise DataFileError(path, f"not a readable .npz file ({type(error).__name__}: {error})", remedy) from None


#: Bytes before a zip member's name in its local header, and where the name's and the extra field's lengths are.
_LOCAL_HEADER_BYTES, _LOCAL_HEADER_LENGTHS = 30, slice(26, 30)


def _mapped_members(path: str | os.PathLike, remedy: str) -> dict[str, np.ndarray]:
    """Each ``.npy`` member of an uncompressed ``.npz`` (checked by `check_npz`) as a read-only
    ``numpy.memmap``. By hand: numpy maps ``.npy`` files only, not an archive's members, whose data
    sits at an offset the zip's local header gives."""
    arrays = {}
    with zipfile.ZipFile(path) as archive, open(path, "rb") as stream:
        for member in archive.infolist():
            name = member.filename.removesuffix(".npy")
            if member.compress_type != zipfile.ZIP_STORED:
                raise DataFileError(path, f"member {member.filename!r} is compressed: it cannot be mapped", remedy)
            stream.seek(member.header_offset)
            name_length, extra_length = struct.unpack("<HH", stream.read(_LOCAL_HEADER_BYTES)[_LOCAL_HEADER_LENGTHS])
            stream.seek(member.header_offset + _LOCAL_HEADER_BYTES + name_length + extra_length)
            version = np.lib.format.read_magic(stream)
            read_header = (
                np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            )
            shape, fortran_order, dtype = read_header(stream)
            if dtype.hasobject:
                raise DataFileError(path, f"member {member.filename!r} holds Python objects", remedy)
            if 0 in shape:  # numpy cannot map zero bytes
                arrays[name] = np.empty(shape, dtype=dtype)
                continue
            order = "F" if fortran_order else "C"
            arrays[name] = np.memmap(path, dtype=dtype, mode="r", offset=stream.tell(), shape=shape, order=order)
    return arrays


class NotCached(LookupError):
    """Arrays `cached_arrays` would compute, asked for within `stored_only`; ``path``: where they would be."""

    def __init__(self, path: str | os.PathLike | None) -> None:
        self.path = path
        super().__init__(f"not cached: {path}")


_stored_only = contextvars.ContextVar("stored_only", default=False)


@contextlib.contextmanager
def stored_only() -> Iterator[None]:
    """Within it (in this thread), `cached_arrays` computes nothing: what is not stored raises
    `NotCached` (a dry run's look at what the caches already hold)."""
    token = _stored_only.set(True)
    try:
        yield
    finally:
        _stored_only.reset(token)


def cached_arrays(
    path: str | os.PathLike | None, compute: Callable[[], Mapping[str, np.ndarray]]
) -> tuple[dict[str, np.ndarray], bool]:
    """``(arrays, hit)``: the arrays stored at ``path``, else ``compute()`` saved there (within
    `stored_only`: `NotCached` instead).

    Processes sharing the cache (the jobs of a sharded evaluation or a multirun) compute it once:
    the first holds the hidden ``.<name>.lock`` beside it while it computes, the others wait and read what it saved.
    ``path=None`` disables caching (always computes, ``hit`` False).
    """
    if path is not None and Path(path).is_file():
        return load_arrays(path), True
    if _stored_only.get():
        raise NotCached(path)
    if path is None:
        return dict(compute()), False
    from filelock import FileLock

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with FileLock(Path(path).parent / f".{Path(path).name}.lock"):
        if Path(path).is_file():  # computed by another process while this one waited
            return load_arrays(path), True
        arrays = dict(compute())
        save_arrays(path, arrays)
    return arrays, False


def file_signature(path: str | os.PathLike | None) -> tuple[int, int]:
    """``(size in bytes, modification time in ns)`` of a file, ``(-1, -1)`` if absent: part of cache keys."""
    try:
        status = os.stat(path) if path is not None else None
    except FileNotFoundError:
        status = None
    return (status.st_size, status.st_mtime_ns) if status is not None else (-1, -1)


def tree_signature(path: str | os.PathLike) -> list[tuple[str, int, int]]:
    """``(relative path, size, modification time in ns)`` of every file under a folder, sorted;
    ``[("", size, time)]`` for a file and ``[]`` for a missing path: part of cache keys."""
    if os.path.isfile(path):
        return [("", *file_signature(path))]
    entries = []
    for root, _, names in os.walk(path):
        for name in names:
            file = os.path.join(root, name)
            entries.append((os.path.relpath(file, path), *file_signature(file)))
    return sorted(entries)
