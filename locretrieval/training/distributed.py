"""Several training processes (Lightning DDP, one per device, on one node or several) working as one.

A step's loss sees the union of every rank's batch (`RetrievalTraining`); the validation and the
hard-negative miner split their work over the ranks and exchange the results, so that every rank
holds what one process would have computed:

- images are described in shards of whole extraction batches (`describe_across_ranks`: each
  batch is the one a single process would run, so the descriptors are the same);
- the SfM paradigms' work is split with the evaluation's own sharding (`Shard`)
  into the shared cache, then assembled by rank 0;
- every exchange carries each rank's outcome (`Ranks.gather`, `Ranks.first`): a rank whose work
  raised ends every rank with its error (`RankFailed`) instead of leaving the others waiting in
  a collective.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import torch

from locretrieval.models.base import GlobalDescriptor
from locretrieval.models.extraction import size_batches
from locretrieval.models.torch_descriptor import TorchGlobalDescriptor
from locretrieval.scene import ImageSet
from locretrieval.shard import Shard

Result = TypeVar("Result")


class RankFailed(RuntimeError):
    """Another rank's share of the work raised: its rank, exception and traceback."""


@dataclass(frozen=True)
class Ranks:
    """The processes of a run: this one's ``index`` (the global rank) of ``count``. With one
    process every method runs the work here and raises its own exceptions unchanged."""

    index: int
    count: int

    @classmethod
    def of(cls, trainer: Any) -> Ranks:
        """The ranks of a Lightning trainer."""
        return cls(trainer.global_rank, trainer.world_size)

    @property
    def shard(self) -> Shard:
        """This rank's share of a list of work items (every ``count``-th from ``index``)."""
        return Shard(self.index, self.count)

    def gather(self, work: Callable[[], Result]) -> list[Result]:
        """``work()`` on every rank; every rank's result on every rank, in rank order. When it
        raised on a rank, that rank raises its exception and every other one `RankFailed`."""
        outcome = _attempt(work)
        if self.count == 1:
            return [_result(outcome, 0, self.index)]
        outcomes: list[Any] = [None] * self.count
        torch.distributed.all_gather_object(outcomes, _shareable(outcome))
        for rank, other in enumerate(outcomes):  # the first failure, the same on every rank
            if other[1] is not None:
                _result(outcome if rank == self.index else other, rank, self.index)
        return [result for result, _ in outcomes]

    def first(self, work: Callable[[], Result]) -> Result:
        """``work()`` on rank 0, its result on every rank; when it raised, rank 0 raises its
        exception and every other rank `RankFailed`."""
        outcome = _attempt(work) if self.index == 0 else None
        if self.count > 1:
            box = [_shareable(outcome) if self.index == 0 else None]
            torch.distributed.broadcast_object_list(box, src=0)
            outcome = outcome if self.index == 0 else box[0]
        return _result(outcome, 0, self.index)


def _attempt(work: Callable[[], Result]) -> tuple[Result | None, Exception | None]:
    """``(result, None)``, or ``(None, error)`` when ``work`` raised."""
    try:
        return work(), None
    except Exception as error:  # handed to every rank; raised again on this one
        return None, error


def _shareable(outcome: tuple[Any, Exception | None]) -> tuple[Any, str | None]:
    """An outcome as it travels to the other ranks: an exception as its traceback's text (an
    exception need not pickle)."""
    result, error = outcome
    return (result, None) if error is None else (None, "".join(traceback.format_exception(error)))


def _result(outcome: tuple[Any, Any], rank: int, here: int) -> Any:
    """The result of ``rank``'s outcome (this rank's own, or another's as `_shareable` made it),
    or its exception raised: this rank's as it is, another's as `RankFailed` with its traceback."""
    result, error = outcome
    if error is None:
        return result
    if rank == here:
        raise error
    raise RankFailed(f"rank {rank} failed, so every rank stops:\n{error}")


def extraction_batches(model: GlobalDescriptor, images: ImageSet) -> list[list[int]]:
    """The batches of image indices ``model.describe(images)`` runs: a torch model's (equal
    sizes, ``extraction.batch_size`` each), one image each for any other model."""
    batch_size = model.settings.batch_size if isinstance(model, TorchGlobalDescriptor) else 1
    return size_batches([(camera.width, camera.height) for camera in images.cameras], batch_size)


def describe_across_ranks(model: GlobalDescriptor, images: ImageSet, ranks: Ranks) -> np.ndarray:
    """``model.describe(images)`` on every rank, each describing every ``count``-th of its
    extraction batches (`extraction_batches`: the batches one process runs, so the descriptors
    are the ones it computes)."""
    if ranks.count == 1:
        return model.describe(images)
    batches = extraction_batches(model, images)
    rows = [
        np.array([i for batch in Shard(rank, ranks.count).take(batches) for i in batch], dtype=np.int64)
        for rank in range(ranks.count)
    ]
    mine = rows[ranks.index]
    parts = ranks.gather(lambda: model.describe(images.subset(mine)) if len(mine) else None)
    shape = next(part.shape[1:] for part in parts if part is not None)
    descriptors = np.empty((len(images), *shape), dtype=np.float32)
    for part, taken in zip(parts, rows, strict=True):
        if part is not None:
            descriptors[taken] = part
    return descriptors
