"""`ShardedStore`: a folder of HDF5 files holding keyed records of arrays, written atomically.

Local features and matches are computed in batches by worker processes; each batch becomes
one new shard file (moved into place only when complete), so a killed run loses at most
the batches in flight and a restarted one computes only the records still missing. Shards
are never modified after they are written, which makes concurrent readers safe.

A record is a set of named arrays (the same names in every record of a shard) stored under
a key (any string, e.g. an image name or a pair of them). A shard stores, per array name,
the records' arrays concatenated along their first axis with their lengths, and the keys in
order, so reading a shard is a few dataset reads. Readers may ask for some of the arrays only
(e.g. keypoints without descriptors): each array of a shard is read on first use and recently
read ones stay in memory, up to `CACHED_BYTES` per store. An array larger than `WHOLE_ARRAY_BYTES`
(at the published datasets' 20,000 keypoints, a shard's descriptors are hundreds of MB) is read
record by record, those asked for only: a pair's cost then does not grow with the shard it lies in.
"""

from __future__ import annotations

import contextlib
import threading
from collections import OrderedDict
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from locretrieval.bounded_files import hdf5_member, open_hdf5, read_dataset
from locretrieval.cache import atomic_path, config_key
from locretrieval.errors import DELETE_CACHE_FILE, DataFileError

if TYPE_CHECKING:
    import h5py  # imported where it is used: a run without local features does not load it

SHARD_SUFFIX = ".h5"
#: Bytes of shard arrays kept in memory per store (least recently used dropped first).
CACHED_BYTES = 512 * 2**20
#: A shard's array of more bytes than this is read record by record (those asked for), a smaller
#: one whole on first use (the records asked for next are likely in it, and it stays in the cache).
WHOLE_ARRAY_BYTES = CACHED_BYTES // 16

#: One array of every record of a shard: ``key -> array``.
Column = dict[str, np.ndarray]


class ShardedStore:
    """Records ``key -> {array name: array}`` spread over the shard files of ``folder``. The index
    changes under a lock: the pipeline's matching thread writes and refreshes it while the main
    thread pickles the store for the worker processes."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self._index: dict[str, Path] | None = None
        self._stale = False
        self._array_names: dict[Path, list[str]] = {}
        self._cache: OrderedDict[tuple[Path, str], Column] = OrderedDict()
        self._cached_bytes = 0
        self._lock = threading.Lock()

    def __getstate__(self) -> dict:
        """Pickled for worker processes without the in-memory shards, with the index and the list
        of read shards copied together between two changes: a list naming a shard whose keys the
        index lacks makes a worker skip that shard."""
        with self._lock:
            state = {**self.__dict__, "_cache": OrderedDict(), "_cached_bytes": 0}
            state["_index"] = None if self._index is None else dict(self._index)
            state["_array_names"] = dict(self._array_names)
        del state["_lock"]
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    @property
    def index(self) -> dict[str, Path]:
        """Key -> shard holding it, read from the shard files on first use, then from the shards
        written since when asked to (`refresh`)."""
        with self._lock:
            return self._read_index()

    def _read_index(self) -> dict[str, Path]:
        if self._index is None or self._stale:
            index = self._index or {}
            # "[!.]": not the hidden temporary files of shards being written (`atomic_path`)
            shards = sorted(self.folder.glob(f"[!.]*{SHARD_SUFFIX}")) if self.folder.is_dir() else []
            if not set(self._array_names) <= set(shards):  # shards deleted (the cache cleared): read all again
                index, self._array_names = {}, {}
            for shard in shards:
                if shard in self._array_names:  # read before: shards are never modified
                    continue
                with _open(shard) as file:
                    index.update((key, shard) for key in _read(file, "keys", shard, text=True))
                    self._array_names[shard] = sorted(_member(file, "data", shard))
            self._index, self._stale = index, False
        return self._index

    def refresh(self) -> None:
        """See the shards written since the index was read (by this or other processes)."""
        self._stale = True

    def __contains__(self, key: str) -> bool:
        return key in self.index

    def __len__(self) -> int:
        return len(self.index)

    def missing(self, keys: Iterable[str]) -> list[str]:
        """The keys without a record, in the given order, without repeats."""
        index = self.index
        return list(dict.fromkeys(key for key in keys if key not in index))

    def read(self, keys: Iterable[str], arrays: Sequence[str] | None = None) -> dict[str, dict[str, np.ndarray]]:
        """The records of ``keys`` holding the arrays named in ``arrays`` (all when None), and
        only those are read from disk; a missing key or array is a `KeyError`."""
        keys = list(dict.fromkeys(keys))
        by_shard: dict[Path, list[str]] = {}
        for key in keys:
            shard = self.index.get(key)
            if shard is None:
                raise KeyError(f"{self.folder}: no record {key!r}")
            by_shard.setdefault(shard, []).append(key)
        records: dict[str, dict[str, np.ndarray]] = {key: {} for key in keys}
        for shard, shard_keys in by_shard.items():
            names = self._array_names[shard] if arrays is None else arrays
            for name, column in self._columns(shard, names, shard_keys).items():
                for key in shard_keys:
                    records[key][name] = column[key]
        return records

    def _columns(self, shard: Path, names: Sequence[str], keys: Sequence[str]) -> dict[str, Column]:
        """The arrays ``names`` of the records ``keys`` of ``shard`` (of every record where an array
        is read whole, `WHOLE_ARRAY_BYTES`), read on first use and cached."""
        unread = {name: [key for key in keys if key not in self._cache.get((shard, name), {})] for name in names}
        unread = {name: missing for name, missing in unread.items() if missing}
        if unread:
            with _open(shard) as file:
                shard_keys = list(_read(file, "keys", shard, text=True))
                data = _member(file, "data", shard)
                for name, missing in unread.items():
                    if name not in data:
                        raise KeyError(f"cache shard {shard} has no array {name!r}; it holds {sorted(data)}")
                    column = self._cache.setdefault((shard, name), {})
                    read = _records(file, shard, name, shard_keys, missing)
                    self._cached_bytes += sum(array.nbytes for key, array in read.items() if key not in column)
                    column.update(read)
        columns = {}
        for name in names:
            self._cache.move_to_end((shard, name))
            columns[name] = self._cache[(shard, name)]
        while self._cached_bytes > CACHED_BYTES and len(self._cache) > len(names):
            _, dropped = self._cache.popitem(last=False)
            self._cached_bytes -= sum(array.nbytes for array in dropped.values())
        return columns

    def write(self, records: Mapping[str, Mapping[str, np.ndarray]]) -> Path | None:
        """Store ``records`` (same array names in each) as one new shard, atomically."""
        if not records:
            return None
        keys = list(records)
        names = sorted(records[keys[0]])
        if any(sorted(arrays) != names for arrays in records.values()):
            raise ValueError(f"{self.folder}: records of one shard must hold the same arrays {names}")
        path = self.folder / f"{config_key(sorted(keys))}{SHARD_SUFFIX}"
        import h5py

        with atomic_path(path) as temporary:
            with h5py.File(temporary, "w") as file:
                file.create_dataset("keys", data=np.array(keys, dtype=object), dtype=h5py.string_dtype())
                for name in names:
                    arrays = [np.asarray(records[key][name]) for key in keys]
                    file.create_dataset(f"data/{name}", data=np.concatenate(arrays))
                    file.create_dataset(f"lengths/{name}", data=np.array([len(a) for a in arrays], dtype=np.int64))
        with self._lock:
            if self._index is not None:
                self._index.update((key, path) for key in keys)
                self._array_names[path] = names
        return path


def _open(shard: Path) -> contextlib.AbstractContextManager[h5py.File]:
    """``shard`` open for reading; a shard that cannot be opened or read (damaged, truncated: h5py's
    ``OSError``) is a `DataFileError` naming it and saying to delete it (its records are recomputed)."""
    return open_hdf5(shard, "cache shard", DELETE_CACHE_FILE)


def _member(file: h5py.File, name: str, shard: Path) -> h5py.Group | h5py.Dataset:
    """The group or dataset ``name`` of a shard (no link followed: `hdf5_member`); a `DataFileError` when absent."""
    member = hdf5_member(file, name, shard, DELETE_CACHE_FILE)
    if member is None:
        raise DataFileError(shard, f"not a cache shard: it has no {name!r}", DELETE_CACHE_FILE)
    return member


def _records(file: h5py.File, shard: Path, name: str, keys: Sequence[str], wanted: Sequence[str]) -> Column:
    """Array ``name`` of every record of an open shard whose keys are ``keys`` (in order), or of the
    records ``wanted`` only when the array exceeds `WHOLE_ARRAY_BYTES` (one read of its rows each)."""
    lengths = _read(file, f"lengths/{name}", shard)
    dataset = _member(file, f"data/{name}", shard)
    if dataset.size * dataset.dtype.itemsize <= WHOLE_ARRAY_BYTES:
        return dict(zip(keys, np.split(_read(file, f"data/{name}", shard), np.cumsum(lengths)[:-1])))
    ends, row = np.cumsum(lengths), {key: index for index, key in enumerate(keys)}
    return {
        key: read_dataset(
            dataset, shard, DELETE_CACHE_FILE, rows=slice(ends[row[key]] - lengths[row[key]], ends[row[key]])
        )
        for key in wanted
    }


def _read(file: h5py.File, name: str, shard: Path, text: bool = False) -> np.ndarray:
    """The dataset ``name`` of a shard, read within its budget (`read_dataset`)."""
    return read_dataset(_member(file, name, shard), shard, DELETE_CACHE_FILE, text)
