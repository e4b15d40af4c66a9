"""The verbs of the SfM pipeline, each a plain function of what it works on (as hloc's modules are
verbs on files): `extract_pair_features` (the local features of the images of some pairs),
`match_and_verify` (query and database pairs, each store in one pass) and `stream_chunks` (queries
in chunks, one chunk localised while the next is matched); `StageMeter` times each stage where it
runs and shows its progress. Triangulating maps with known poses (`locretrieval.sfm.triangulation`)
and registering queries in them (`locretrieval.sfm.registration`) are the verbs of their own modules.

Nothing here knows a paradigm: the SfM paradigms (`locretrieval.paradigms.sfm`) say which pairs,
maps and registrations they need and call these verbs with them.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

from tqdm import tqdm

from locretrieval.estimates import PoseEstimates
from locretrieval.pool import cpu_time, progress_to
from locretrieval.sfm.features import extract_features
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.work import SfmPlan
from locretrieval.shard import Shard

#: A pair of image names: (query, database image) or (database image, database image).
Pair = tuple[str, str]
#: Queries per chunk of the streamed stages (a chunk is triangulated and registered while the next is matched).
QUERIES_PER_CHUNK = 512


@dataclass
class StageRecord:
    """What a stage did in a run: its ``seconds`` of work (summed over its calls; stages overlap,
    so a run's records may add up to more than its time), its ``cpu_seconds`` (this process's while
    it ran and its tasks' in the worker processes, `cpu_time`; overlapping stages share this
    process's) and its ``done`` work in its ``unit``."""

    seconds: float = 0.0
    done: int = 0
    unit: str = ""
    cpu_seconds: float = 0.0

    def __str__(self) -> str:
        rate = f", {self.done / self.seconds:,.1f}/s" if self.done and self.seconds > 0 else ""
        return f"{self.done:,} {self.unit} in {self.seconds:.1f} s{rate}"


class StageMeter:
    """Times each stage where it runs and shows its progress in its own units: ``with meter(stage):
    ...`` (from several threads) adds the block's seconds and CPU seconds to the stage's record, and the tasks its
    worker pools finish to the stage's bar (tqdm: rate and time left from the stage's throughput so
    far) of the ``planned`` work (stage -> (units, unit name), `SfmPlan.stage_units`)."""

    def __init__(self, planned: Mapping[str, tuple[int | None, str]]) -> None:
        self.planned = dict(planned)
        self.records = {stage: StageRecord(unit=unit) for stage, (_, unit) in self.planned.items()}
        self._bars: dict[str, Any] = {}
        self._lock = threading.Lock()

    def advance(self, stage: str, units: int) -> None:
        """Count ``units`` of ``stage``'s work done (e.g. a map built in this process)."""
        with self._lock:
            record = self.records.setdefault(stage, StageRecord())
            record.done += units
            if stage not in self._bars:
                total, unit = self.planned.get(stage, (None, "tasks"))
                self._bars[stage] = tqdm(total=total, desc=stage, unit=f" {unit}", disable=None, leave=False)
            self._bars[stage].update(units)

    @contextlib.contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        started = time.perf_counter()
        try:
            with cpu_time() as cpu, progress_to(lambda units: self.advance(stage, units)):
                yield
        finally:
            with self._lock:
                record = self.records.setdefault(stage, StageRecord())
                record.seconds += time.perf_counter() - started
                record.cpu_seconds += cpu.seconds

    def close(self) -> dict[str, StageRecord]:
        """Close the bars; every stage's record."""
        for bar in self._bars.values():
            bar.close()
        return self.records


@dataclass
class SfmRun:
    """What a run of the SfM paradigms (`locretrieval.paradigms.sfm.run_sfm`) returns: the pose
    ``estimates`` by paradigm (None for a share of the queries), the ``plan`` it counted first, each
    stage's `StageRecord` and the run's ``seconds`` (wall clock)."""

    estimates: dict[str, list[PoseEstimates]] | None
    plan: SfmPlan
    stages: dict[str, StageRecord]
    seconds: float


def extract_pair_features(
    inputs: SfmInputs,
    shard: Shard | None,
    query_pairs: Sequence[Pair],
    database_pairs: Sequence[Pair],
) -> None:
    """Local features of every image of both sets (a shard's share of each), then
    of the images of the (query, database) and (database, database) pairs still missing."""
    scene, settings, workers, cache_dir = inputs.scene, inputs.settings, inputs.settings.processes, inputs.cache_dir
    needed = (
        (
            scene.database,
            sorted({name for _, name in query_pairs} | {name for pair in database_pairs for name in pair}),
        ),
        (scene.queries, sorted({query for query, _ in query_pairs})),
    )
    for images, names in needed:
        extract_features(
            images, settings.features, cache_dir, workers, None if shard is None else shard.take(images.names)
        )
        extract_features(images, settings.features, cache_dir, workers, names)
    for store in (inputs.database_features, inputs.query_features):
        store.store.refresh()  # the run's stores, counted before: their indexes now hold the new features


def match_and_verify(inputs: SfmInputs, query_pairs: Sequence[Pair], database_pairs: Sequence[Pair]) -> None:
    """Match and verify every query pair and every database pair (each store in one pass)."""
    workers = inputs.settings.processes
    inputs.query_pairs.ensure(query_pairs, workers, inputs.query_verification)
    inputs.database_pairs.ensure(database_pairs, workers, inputs.database_verification)


def stream_chunks(
    queries: Sequence[int], match: Callable[[Sequence[int]], None], localize: Callable[[Sequence[int]], None]
) -> None:
    """``match(chunk)`` then ``localize(chunk)`` for each chunk of `QUERIES_PER_CHUNK` ``queries``:
    while one chunk is localised (a thread driving the worker processes), the next one is matched
    (on the GPU, or the workers); one chunk is localised at a time."""
    with ThreadPoolExecutor(1, thread_name_prefix="sfm-localize") as background:
        localizing = None
        for start in range(0, len(queries), QUERIES_PER_CHUNK):
            chunk = queries[start : start + QUERIES_PER_CHUNK]
            match(chunk)
            if localizing is not None:
                localizing.result()  # one chunk localised at a time: the worker processes are its
            localizing = background.submit(localize, chunk)
        if localizing is not None:
            localizing.result()
