"""Compressed and linked files read within budgets: zip archives (``.npz``, torch checkpoints),
MATLAB ``.mat`` files and HDF5 files.

A compressed member may expand to at most ``limits.compression_ratio`` times its stored bytes
(plus `locretrieval.limits.SLACK_BYTES`): deflate reaches about 1000:1, so 0.5 MB of zeros became
512 MB before any reader looked at them. What each format declares is checked before anything is
decompressed or allocated:

- zip (`check_zip`): every member's uncompressed size as the central directory states it (Python's
  ``zipfile`` and torch's reader stop there); in an ``.npz`` (`check_npz`) also each ``.npy``
  header's shape x itemsize against its member (``numpy.load`` allocates what the header says
  before reading);
- MATLAB v5 (`check_mat`): each compressed element inflated into a bounded buffer (never more
  than its budget), then every matrix walked: a cell or struct array may not declare more elements
  than the bytes that hold them (scipy allocates ``prod(dims)`` objects first);
- HDF5 (`hdf5_member`, `read_dataset`): no link but hard links is followed (an ``ExternalLink``
  opens another file, a soft link may lead through one), no dataset with external storage or a
  virtual layout (their bytes live in other files) is read, and a dataset's bytes are bounded by
  what the file stores for it (an unwritten compressed dataset reads as its fill value: 3.4 KB of
  file became a 512 MB array).

Every refusal is a `DataFileError` naming the file, the member and the key of the budget.
"""

from __future__ import annotations

import contextlib
import math
import mmap
import os
import struct
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from locretrieval import limits
from locretrieval.errors import FIX_DATA_FILE, DataFileError

if TYPE_CHECKING:
    import h5py

RATIO_KEY = "limits.compression_ratio"
#: What h5py raises on a damaged file (HDF5's errors mapped to Python's, a few as RuntimeError).
H5PY_ERRORS = (OSError, RuntimeError)


def expansion_budget(stored_bytes: int) -> int:
    """Bytes that ``stored_bytes`` of compressed data may expand to (``limits.compression_ratio``)."""
    budgets = limits.current()
    return budgets.size_budget(stored_bytes, budgets.compression_ratio)


def _too_large(
    path: str | os.PathLike, what: str, size: int | str, stored: int, remedy: str, when: str = "before decompressing"
) -> DataFileError:
    return DataFileError(
        path,
        f"{what} would expand to {size} bytes from {stored} stored, more than {expansion_budget(stored)} "
        f"({RATIO_KEY} x stored + 1 MiB); refused {when}",
        remedy,
    )


# --- zip ----------------------------------------------------------------------------------------


def check_zip(path: str | os.PathLike, remedy: str = FIX_DATA_FILE, kind: str = "zip archive") -> list[zipfile.ZipInfo]:
    """The members of the zip archive ``path`` (its central directory only, nothing decompressed),
    each within its expansion budget; a `DataFileError` otherwise or when it is not a readable ``kind``."""
    try:
        with zipfile.ZipFile(path) as archive:
            members = archive.infolist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as error:
        if isinstance(error, FileNotFoundError):
            raise
        raise DataFileError(path, f"not a readable {kind} ({type(error).__name__}: {error})", remedy) from None
    for member in members:
        if member.file_size > expansion_budget(member.compress_size):
            raise _too_large(path, f"member {member.filename!r}", member.file_size, member.compress_size, remedy)
    return members


def check_npz(path: str | os.PathLike, remedy: str = FIX_DATA_FILE) -> None:
    """`check_zip`, and every ``.npy`` member's header (shape x itemsize) equal to the bytes it holds."""
    members = check_zip(path, remedy, ".npz file")
    try:
        with zipfile.ZipFile(path) as archive:
            for member in members:
                if member.filename.endswith(".npy"):
                    with archive.open(member) as stream:
                        _check_npy_header(path, f"member {member.filename!r}", member.file_size, stream, remedy)
    except (DataFileError, FileNotFoundError):  # gone since `check_zip` (a concurrent merge): the caller's case
        raise
    except Exception as error:  # zipfile and numpy's header reader raise many types on damage
        raise DataFileError(path, f"not a readable .npz file ({type(error).__name__}: {error})", remedy) from None


def check_npy(path: str | os.PathLike, remedy: str = FIX_DATA_FILE) -> None:
    """An ``.npy`` file's header (shape x itemsize) equal to the bytes it holds (``numpy.load``
    allocates what the header says before reading)."""
    try:
        with open(path, "rb") as stream:
            _check_npy_header(path, "its header", os.fstat(stream.fileno()).st_size, stream, remedy)
    except (DataFileError, FileNotFoundError):
        raise
    except Exception as error:  # numpy's header reader raises many types on damage
        raise DataFileError(path, f"not a readable .npy file ({type(error).__name__}: {error})", remedy) from None


def _check_npy_header(path: str | os.PathLike, what: str, size: int, stream: Any, remedy: str) -> None:
    """The ``.npy`` data in ``stream`` (``size`` bytes with its header) holds what its header declares."""
    version = np.lib.format.read_magic(stream)
    read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, _, dtype = read_header(stream)
    if dtype.hasobject:
        return  # refused by numpy.load(allow_pickle=False) itself, before reading any data
    declared = math.prod(shape) * dtype.itemsize
    held = size - stream.tell()
    if declared != held:
        raise DataFileError(
            path,
            f"{what} declares an array of shape {shape} and dtype {dtype} ({declared} bytes) but holds {held} bytes",
            remedy,
        )


# --- MATLAB ---------------------------------------------------------------------------------------

MAT_HEADER = 128
MI_MATRIX, MI_COMPRESSED = 14, 15
#: MATLAB classes whose arrays hold other matrices (cell 1, struct 2, object 3): scipy allocates their elements first.
CELL, STRUCT, OBJECT = 1, 2, 3
#: Bytes of the smallest element a cell or struct holds (a tag).
TAG_BYTES = 8
#: Matrices nested at most this deep (cells of structs of ...).
MAT_DEPTH = 64


def check_mat(path: str | os.PathLike, remedy: str = FIX_DATA_FILE) -> None:
    """Check a MATLAB v5 ``.mat`` file within its budgets (module docstring); v4 and v7.3 (HDF5)
    files are left to scipy's reader, which refuses the latter."""
    with open(path, "rb") as stream:
        size = os.fstat(stream.fileno()).st_size
        if size < MAT_HEADER:
            return  # scipy says what it is not
        with mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as data:
            order = {b"IM": "<", b"MI": ">"}.get(bytes(data[126:128]))
            version = struct.unpack(f"{order}H", data[124:126])[0] if order else None
            if order is None or version != 0x0100:
                return
            position = MAT_HEADER
            while position + TAG_BYTES <= size:
                kind, length, start = _tag(data, position, size, order, path, remedy)
                if kind == MI_COMPRESSED:
                    inflated = _inflate(data[start : start + length], path, f"element at byte {position}", remedy)
                    _check_elements(inflated, 0, len(inflated), order, path, remedy, 0)
                elif kind == MI_MATRIX:
                    _check_matrix(data, start, start + length, order, path, remedy, 0)
                position = start + length


def _inflate(compressed: bytes, path: str | os.PathLike, what: str, remedy: str) -> bytes:
    """``compressed`` (zlib) inflated, or a `DataFileError` as soon as it outgrows its budget."""
    budget = expansion_budget(len(compressed))
    inflater = zlib.decompressobj()
    parts, total = [], 0
    pending = compressed
    try:
        while pending and not inflater.eof:
            part = inflater.decompress(pending, 1 << 20)
            pending = inflater.unconsumed_tail
            total += len(part)
            if total > budget:
                raise _too_large(
                    path, what, f"more than {total}", len(compressed), remedy, "as it inflated, nothing kept"
                )
            parts.append(part)
    except zlib.error as error:
        raise DataFileError(path, f"{what}: not readable compressed data ({error})", remedy) from None
    return b"".join(parts)


def _tag(data: Any, position: int, end: int, order: str, path: Any, remedy: str) -> tuple[int, int, int]:
    """``(type, bytes, data start)`` of the element at ``position`` (the small format packs both in 4 bytes)."""
    end = min(end, len(data))
    if position + TAG_BYTES > end:
        raise DataFileError(path, f"a MATLAB element at byte {position} is cut short", remedy)
    first, second = struct.unpack(f"{order}II", data[position : position + TAG_BYTES])
    if first >> 16:  # small data element: bytes in the upper half (4 at most), data in the next 4 bytes
        if first >> 16 > 4:
            raise DataFileError(path, f"a small MATLAB element at byte {position} declares {first >> 16} bytes", remedy)
        return first & 0xFFFF, first >> 16, position + 4
    if position + TAG_BYTES + second > end:
        raise DataFileError(
            path, f"a MATLAB element at byte {position} declares {second} bytes past the end of what holds it", remedy
        )
    return first, second, position + TAG_BYTES


def _next(start: int, length: int, small: bool) -> int:
    """Where the element after one of ``length`` bytes at ``start`` begins (8-byte aligned)."""
    return start + 4 if small else start + length + (-length % 8)


def _check_elements(data: Any, position: int, end: int, order: str, path: Any, remedy: str, depth: int) -> None:
    while position + TAG_BYTES <= end:
        kind, length, start = _tag(data, position, end, order, path, remedy)
        if kind == MI_MATRIX:
            _check_matrix(data, start, start + length, order, path, remedy, depth)
        position = start + length


def _check_matrix(data: Any, position: int, end: int, order: str, path: Any, remedy: str, depth: int) -> None:
    """A matrix's sub-elements (flags, dims, name, then its class's); a cell or struct may declare
    no more elements than its bytes can hold, and each is checked in turn."""
    if depth > MAT_DEPTH:
        raise DataFileError(path, f"MATLAB matrices nested deeper than {MAT_DEPTH}", remedy)
    if position == end:
        return  # an empty matrix
    parts = []
    for _ in range(3):  # array flags, dimensions, name
        kind, length, start = _tag(data, position, end, order, path, remedy)
        parts.append(bytes(data[start : start + length]))
        position = _next(start, length, start - position == 4)
    if len(parts[0]) < 4 or len(parts[1]) % 4:
        raise DataFileError(path, "a MATLAB matrix without its array flags or dimensions", remedy)
    matrix_class = struct.unpack(f"{order}I", parts[0][:4])[0] & 0xFF
    elements = math.prod(struct.unpack(f"{order}{len(parts[1]) // 4}i", parts[1]))
    if matrix_class not in (CELL, STRUCT, OBJECT):
        return
    fields = 1
    if matrix_class == OBJECT:  # its class name, then as a struct
        kind, length, start = _tag(data, position, end, order, path, remedy)
        position = _next(start, length, start - position == 4)
    if matrix_class in (STRUCT, OBJECT):  # the field name length, then the names
        kind, length, start = _tag(data, position, end, order, path, remedy)
        name_length = struct.unpack(f"{order}i", bytes(data[start : start + 4]))[0] if length >= 4 else 0
        position = _next(start, length, start - position == 4)
        kind, length, start = _tag(data, position, end, order, path, remedy)
        fields = length // name_length if name_length > 0 else 0
        position = _next(start, length, start - position == 4)
    if elements < 0 or elements * max(fields, 1) * TAG_BYTES > end - position:
        raise DataFileError(
            path,
            f"a MATLAB {('cell', 'struct', 'object')[matrix_class - 1]} array declares {elements} x {fields} "
            f"elements in {end - position} bytes",
            remedy,
        )
    _check_elements(data, position, end, order, path, remedy, depth + 1)


# --- HDF5 -----------------------------------------------------------------------------------------


@contextlib.contextmanager
def open_hdf5(path: str | os.PathLike, what: str, remedy: str) -> Iterator[h5py.File]:
    """``path`` open for reading; a file that cannot be opened or read (damaged, truncated: h5py's
    ``OSError``) is a `DataFileError` naming it, ``what`` it should be and ``remedy``."""
    import h5py

    if not Path(path).is_file():
        raise FileNotFoundError(f"{what} not found: {path}")
    try:
        with h5py.File(path, "r") as file:
            yield file
    except H5PY_ERRORS as error:
        raise DataFileError(path, f"not a readable {what} ({error})", remedy) from None


def hdf5_member(group: h5py.Group, name: str, path: str | os.PathLike, remedy: str = FIX_DATA_FILE) -> Any:
    """The group or dataset at ``name`` (``/``-separated) below ``group``, ``None`` when absent; a
    soft or external link on the way is a `DataFileError` (it would open another file or path)."""
    import h5py

    node = group
    for part in [part for part in name.split("/") if part]:
        if not isinstance(node, h5py.Group):
            return None
        try:
            link = node.get(part, getlink=True)
            if isinstance(link, h5py.HardLink):
                node = node[part]
                continue
        except (*H5PY_ERRORS, KeyError) as error:  # a damaged file: HDF5's errors as h5py maps them
            raise DataFileError(path, f"not a readable HDF5 file at {name!r} ({error})", remedy) from None
        if link is None:
            return None
        target = getattr(link, "filename", None) or getattr(link, "path", "")
        raise DataFileError(
            path,
            f"{node.name.rstrip('/')}/{part} is a link ({type(link).__name__} to {target}); links are not followed "
            "(only what the file holds is read)",
            remedy,
        )
    return node


def read_dataset(
    dataset: h5py.Dataset,
    path: str | os.PathLike,
    remedy: str = FIX_DATA_FILE,
    text: bool = False,
    rows: slice | None = None,
) -> Any:
    """All of ``dataset`` (``text``: variable-length strings as ``str``), or its ``rows`` (a slice of
    its first axis), after checking that its bytes live in this file (no external storage, no
    virtual layout) and that its size is within the budget of what the file stores for it (module
    docstring)."""
    import h5py

    if not isinstance(dataset, h5py.Dataset):
        raise DataFileError(path, f"{getattr(dataset, 'name', dataset)} is not a dataset", remedy)
    try:
        if dataset.external or dataset.is_virtual:
            where = "external storage" if dataset.external else "a virtual layout (other files)"
            raise DataFileError(path, f"dataset {dataset.name} keeps its data in {where}; refused", remedy)
        size = dataset.size * dataset.dtype.itemsize
        stored = dataset.id.get_storage_size()
        if size > expansion_budget(stored):
            raise _too_large(path, f"dataset {dataset.name}", size, stored, remedy)
        if rows is not None:
            return (dataset.asstr() if text else dataset)[rows]
        return dataset.asstr()[()] if text else dataset[()]
    except (*H5PY_ERRORS, KeyError, ValueError, TypeError) as error:  # a damaged file
        raise DataFileError(path, f"dataset {dataset.name} is not readable ({error})", remedy) from None
