"""The match and verify stages of the SfM pipeline: matches of image pairs, verified, in per-pair caches.

Matching is mutual nearest neighbours with Lowe's ratio test on L2-normalised descriptors
(`locretrieval.sfm.nearest_neighbours`). Matches ``int32 [m, 2]`` hold keypoint indices
(first image, second image). Verification (`locretrieval.sfm.verification`) keeps the
geometrically consistent ones: ``sfm.query_verification`` of query-database pairs,
``sfm.database_verification`` of database pairs (against their known poses).

Where it runs (`MatchingSettings.matcher`):

- on a CPU, worker processes each match and verify a shard of pairs, one pair at a time through
  the cache-blocked `NearestNeighbourMatcher`;
- on a GPU, this process owns the device: pairs are grouped by their first image, each image's
  descriptors are read ahead by a thread, normalised on the device and kept there
  (`DeviceDescriptors`), one image is matched against all its partners per batched product
  (`BatchedMatcher`), and each shard's matches go to the CPU worker processes, which verify
  them and write the stores while the GPU matches the next shard.

Caches, all `ShardedStore`s: ``<cache_dir>/matches/<features 0>--<features 1>--<ratio and
precision key>/`` (raw matches, keyed by the pair of image names) and one store per verification
(``...--poses-<key>/``, ``...--two-view-<key>/``). A pair is matched once whatever k or
verification needed it, and a database pair once in either order.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import groupby
from pathlib import Path
from typing import Any

import numpy as np

from locretrieval.cache import config_key
from locretrieval.config import require
from locretrieval.pool import WORKERS, resolve_workers, split
from locretrieval.scene import ImageSet
from locretrieval.sfm.features import FeatureStore
from locretrieval.sfm.nearest_neighbours import (
    CPU_BLOCK_BYTES,
    PRECISIONS,
    BatchedMatcher,
    DeviceDescriptors,
    NearestNeighbourMatcher,
)
from locretrieval.sfm.store import ShardedStore
from locretrieval.sfm.verification import (
    NoVerification,
    PairVerification,
    VerificationBatch,
    pair_indices,
    verify_pairs,
)

log = logging.getLogger(__name__)

#: Pairs per shard of the cache (one task of a worker).
PAIRS_PER_SHARD = 512
#: Share of a GPU's free memory for one batch of similarities, and for resident descriptors.
GPU_BATCH_SHARE, GPU_DESCRIPTOR_SHARE = 0.25, 0.25
#: Bytes of resident descriptors when the batched matcher runs on the CPU (tests).
HOST_RESIDENT_BYTES = 1 << 30
#: Bump when the meaning of cached matches changes.
CACHE_VERSION = 1

Pair = tuple[str, str]


@dataclass
class MatchingSettings:
    """Mutual nearest neighbours with Lowe's ``ratio`` test (1: off). Matching runs on
    ``device`` (``auto``: CUDA when there is a GPU) with ``precision``
    similarities; ``block_mib`` MiB of them at once (null: `CPU_BLOCK_BYTES` on a CPU, a quarter
    of the free memory on a GPU)."""

    ratio: float
    device: str
    precision: str
    block_mib: float | None

    def __post_init__(self) -> None:
        require(0 < self.ratio <= 1, "ratio", f"must be in (0, 1], got {self.ratio}")
        require(
            self.device == "auto" or self.device.split(":")[0] in ("cpu", "cuda"),
            "device",
            f"must be auto, cpu or cuda[:N], got {self.device!r}",
        )
        require(self.precision in PRECISIONS, "precision", f"must be one of {list(PRECISIONS)}, got {self.precision!r}")
        require(
            self.block_mib is None or self.block_mib > 0,
            "block_mib",
            f"must be a positive number of MiB or null, got {self.block_mib}",
        )

    def identity(self) -> dict[str, Any]:
        """What determines the raw matches (not where or in which blocks they are computed)."""
        return {"ratio": self.ratio, "precision": self.precision}

    def matcher(self) -> NearestNeighbourMatcher | BatchedMatcher:
        """The matcher of these settings in this process: `NearestNeighbourMatcher` on a CPU,
        `BatchedMatcher` on a GPU (batches of ``block_mib``, or a quarter of the free memory)."""
        from locretrieval.device import resolve_device

        device = resolve_device(self.device)
        block_bytes = None if self.block_mib is None else int(self.block_mib * 2**20)
        if device.type == "cuda":
            return BatchedMatcher(
                self.ratio,
                str(device),
                self.precision,
                block_bytes or int(GPU_BATCH_SHARE * free_device_memory(device)),
            )
        return NearestNeighbourMatcher(self.ratio, self.precision, block_bytes or CPU_BLOCK_BYTES)


def free_device_memory(device: Any) -> int:
    """Bytes of the GPU's memory that are free now."""
    import torch

    return torch.cuda.mem_get_info(device)[0]


def pair_key(pair: Pair) -> str:
    return f"{pair[0]}\n{pair[1]}"


class PairMatcher:
    """Cached matches between images of ``images0`` and ``images1`` (the same set: database pairs).

    Pairs are ``(name in images0, name in images1)``. Pairs within one set are stored once in
    a canonical order and returned in the order asked. Raw and verified matches are kept in
    separate stores, so a pair verified two ways is matched once.
    """

    def __init__(
        self,
        images0: ImageSet,
        features0: FeatureStore,
        images1: ImageSet,
        features1: FeatureStore,
        settings: MatchingSettings,
        cache_dir: str | Path,
    ) -> None:
        self.settings = settings
        self.images = (images0, images1)
        self.features = (features0, features1)
        self.same_set = features0.folder == features1.folder
        self.index = tuple({name: i for i, name in enumerate(images.names)} for images in self.images)
        self.root = (
            f"{Path(cache_dir) / 'matches' / f'{features0.folder.name}--{features1.folder.name}'}"
            f"--{config_key(CACHE_VERSION, settings.ratio, settings.precision)}"
        )
        self.raw = ShardedStore(self.root)
        self._verified: dict[PairVerification, ShardedStore] = {}

    def store(self, verification: PairVerification) -> ShardedStore:
        """The store of the matches that ``verification`` keeps (the raw store for `NoVerification`)."""
        if isinstance(verification, NoVerification):
            return self.raw
        if verification not in self._verified:  # its name may hash both image sets: once
            self._verified[verification] = ShardedStore(f"{self.root}--{verification.store_name(*self.images)}")
        return self._verified[verification]

    def _stored(self, pair: Pair) -> tuple[Pair, bool]:
        """The pair as stored, and whether it is the reverse of the one asked."""
        if self.same_set and pair[1] < pair[0]:
            return (pair[1], pair[0]), True
        return pair, False

    def canonical(self, pairs: Iterable[Pair]) -> list[Pair]:
        """Distinct stored forms of ``pairs`` (self-pairs dropped), sorted."""
        stored = {self._stored(pair)[0] for pair in pairs if not (self.same_set and pair[0] == pair[1])}
        for name0, name1 in stored:
            if name0 not in self.index[0] or name1 not in self.index[1]:
                raise KeyError(f"pair {(name0, name1)} is not an image pair of these sets")
        return sorted(stored)

    def todo(self, pairs: Iterable[Pair], verification: PairVerification) -> tuple[list[Pair], set[str], set[str]]:
        """The distinct ``pairs`` (stored forms) whose raw or ``verification``'s matches are not
        cached, and the keys of each kind missing."""
        pairs = self.canonical(pairs)
        verified = self.store(verification)
        for store in {id(self.raw): self.raw, id(verified): verified}.values():
            store.refresh()  # pairs other processes sharing the cache (shards) have matched since are not redone
        missing_raw = set(self.raw.missing(map(pair_key, pairs)))
        missing_verified = set(verified.missing(map(pair_key, pairs))) if verified is not self.raw else set()
        missing = missing_raw | missing_verified
        return [pair for pair in pairs if pair_key(pair) in missing], missing_raw, missing_verified

    def ensure(self, pairs: Iterable[Pair], workers: int | None, verification: PairVerification) -> int:
        """Match and verify the pairs not yet cached; returns how many pairs were matched."""
        todo, missing_raw, missing_verified = self.todo(pairs, verification)
        verified = self.store(verification)
        if not todo:
            return 0
        matcher = self.settings.matcher()
        log.info(
            "matching %d image pairs on %s, verifying %d (%s), into %s",
            len(missing_raw),
            matcher.device,
            len(missing_verified),
            type(verification).__name__,
            self.raw.folder,
        )
        on_device = isinstance(matcher, BatchedMatcher)  # its shards are the device's batches: full ones
        shards = split(todo, PAIRS_PER_SHARD, 1 if on_device else resolve_workers(workers))
        tasks = [
            ShardTask(
                shard,
                missing_raw & set(map(pair_key, shard)),
                missing_verified & set(map(pair_key, shard)),
                verification,
            )
            for shard in shards
        ]
        if on_device:
            self._ensure_on_device(matcher, tasks, workers)
        else:
            for _ in WORKERS.map(_match_shard, tasks, workers, "matching", shared=self, units=_pair_count):
                pass
        self.raw.refresh()
        verified.refresh()
        return len(missing_raw)

    def _ensure_on_device(self, matcher: BatchedMatcher, tasks: Sequence[ShardTask], workers: int | None) -> None:
        """Match every task's new pairs on the device in this process, shard after shard, while a
        thread reads the next shard's descriptors and the CPU workers verify and store the last."""
        import torch

        on_gpu = matcher.device.startswith("cuda")
        capacity = int(GPU_DESCRIPTOR_SHARE * free_device_memory(matcher.device)) if on_gpu else HOST_RESIDENT_BYTES
        resident = [
            DeviceDescriptors(partial_descriptors(store), matcher.device, matcher.dtype, capacity)
            for store in self.features
        ]
        if self.same_set:
            resident[1] = resident[0]

        def read(task: ShardTask) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
            pairs = task.to_match
            return tuple(
                partial_descriptors(store)([name for name in names if name not in held])  # type: ignore[return-value]
                for store, held, names in zip(
                    self.features, resident, (sorted({a for a, _ in pairs}), sorted({b for _, b in pairs}))
                )
            )

        with (
            ThreadPoolExecutor(1) as reader,
            WORKERS.stream(_store_shard, len(tasks), workers, "verifying", self, _pair_count) as submit,
        ):
            upcoming = reader.submit(read, tasks[0])
            for number, task in enumerate(tasks):
                loaded = upcoming.result()
                if number + 1 < len(tasks):
                    upcoming = reader.submit(read, tasks[number + 1])
                found = {}
                for name0, group in groupby(task.to_match, key=lambda pair: pair[0]):
                    partners = [name1 for _, name1 in group]
                    first = resident[0].get([name0], loaded[0])[0]
                    computed = matcher.match(first, resident[1].get(partners, loaded[1]))
                    found.update((pair_key((name0, name1)), matches) for name1, matches in zip(partners, computed))
                submit(dataclasses.replace(task, matched=found))
            if on_gpu:
                torch.cuda.synchronize(matcher.device)

    def load(self, pairs: Sequence[Pair], verification: PairVerification) -> dict[Pair, np.ndarray]:
        """Matches ``int32 [m, 2]`` of each pair (cached with `ensure`), in the order asked."""
        stored = {pair: self._stored(pair) for pair in pairs}
        records = self.store(verification).read(pair_key(s) for s, _ in stored.values())
        result = {}
        for pair, (stored_pair, reversed_) in stored.items():
            matches = records[pair_key(stored_pair)]["matches"]
            result[pair] = matches[:, ::-1] if reversed_ else matches
        return result

    def verify_and_store(self, task: ShardTask, matches: dict[str, np.ndarray]) -> None:
        """Write the task's new raw matches (``matches`` holds them, and may hold cached ones) and
        the verified matches of its pairs to verify, one new shard per store."""
        self.raw.write({key: {"matches": matches[key]} for key in sorted(task.missing_raw)})
        if not task.missing_verified:
            return
        pairs = [pair for pair in task.pairs if pair_key(pair) in task.missing_verified]
        cached = {
            key: record["matches"]
            for key, record in self.raw.read(pair_key(pair) for pair in pairs if pair_key(pair) not in matches).items()
        }
        raw = [matches.get(pair_key(pair), cached.get(pair_key(pair))) for pair in pairs]
        verification = task.verification
        keypoints = [{}, {}]
        if verification.needs_keypoints:
            keypoints = [
                store.keypoints(sorted({pair[side] for pair in pairs})) for side, store in enumerate(self.features)
            ]
        batch = VerificationBatch(*self.images, pair_indices(*self.images, pairs), raw, *keypoints)
        kept = verify_pairs(verification, batch)
        self.store(verification).write({pair_key(pair): {"matches": rows} for pair, rows in zip(pairs, kept)})


@dataclass
class ShardTask:
    """One shard of pairs: those whose raw matches are missing (``missing_raw``, keys) and those
    whose ``verification`` is (``missing_verified``); ``matched``: raw matches computed on the device."""

    pairs: list[Pair]
    missing_raw: set[str]
    missing_verified: set[str]
    verification: PairVerification
    matched: dict[str, np.ndarray] | None = None

    @property
    def to_match(self) -> list[Pair]:
        return [pair for pair in self.pairs if pair_key(pair) in self.missing_raw]


def partial_descriptors(store: FeatureStore):
    """``names -> {name: descriptors}`` of a feature store, without the keypoints."""

    def load(names: Sequence[str]) -> dict[str, np.ndarray]:
        return {
            name: record["descriptors"] for name, record in store.store.read(names, arrays=("descriptors",)).items()
        }

    return load


def _match_shard(matcher: PairMatcher, task: ShardTask) -> int:
    """CPU worker: raw matches of a shard's new pairs, one image against its partners at a time,
    then their verification; written as one new shard per store."""
    pairs = task.to_match
    descriptors0 = partial_descriptors(matcher.features[0])(sorted({name0 for name0, _ in pairs}))
    descriptors1 = partial_descriptors(matcher.features[1])(sorted({name1 for _, name1 in pairs}))
    nearest_neighbours = matcher.settings.matcher()
    found = {}
    for name0, group in groupby(pairs, key=lambda pair: pair[0]):
        partners = [name1 for _, name1 in group]
        computed = nearest_neighbours(descriptors0[name0], [descriptors1[name1] for name1 in partners])
        found.update((pair_key((name0, name1)), matches) for name1, matches in zip(partners, computed))
    matcher.verify_and_store(task, found)
    return len(task.pairs)


def _store_shard(matcher: PairMatcher, task: ShardTask) -> int:
    """CPU worker fed by the device: verify and store a shard whose raw matches came from the GPU."""
    matcher.verify_and_store(task, task.matched or {})
    return len(task.pairs)


def _pair_count(task: ShardTask) -> int:
    """A shard's units of work in the stage's progress: its pairs."""
    return len(task.pairs)
