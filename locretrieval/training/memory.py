"""Cross-batch memory (Wang et al., "Cross-Batch Memory for Embedding Learning", CVPR 2020): the
descriptors of recently trained images, kept without gradient and ranked against each batch's
anchors as extra candidates, so that an anchor is ranked against most of the training images
rather than the few dozen of its batch. `CrossBatchMemory` wraps a loss with one, as
pytorch-metric-learning's ``CrossBatchMemory`` does: every loss of `locretrieval.training.losses`
takes the memory's images unchanged, as candidates of the batch that are no anchor."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from locretrieval.config import require
from locretrieval.training.relevance import TrainingPairs


class DescriptorMemory:
    """The descriptors of the ``size`` images most recently in a batch (the latest copy of each),
    with their rows in the training pairs. A run starts it empty (also when it resumes); under
    DDP every rank remembers the union of the ranks' batches (``module.global_batch``), or with
    per-rank losses its own batches."""

    def __init__(self, size: int) -> None:
        require(size >= 1, "size", f"must be >= 1 (0: no memory), got {size}")
        self.size = size
        self.indices = torch.empty(0, dtype=torch.long)
        self.descriptors: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.indices)

    def extend(
        self,
        descriptors: torch.Tensor,
        relevance: torch.Tensor,
        negatives: torch.Tensor,
        indices: torch.Tensor,
        pairs: TrainingPairs,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The batch (``descriptors [B, D]``, ``relevance`` and ``negatives [B, B]``, the images'
        ``indices`` in ``pairs``) with the remembered images that are not in it appended: descriptors
        ``[B + M, D]``, relevance and negatives ``[B + M, B + M]``. The batch's rows gain its pairs to
        the appended images (from ``pairs``); the appended rows are empty: they are no anchor."""
        if self.descriptors is None:
            return descriptors, relevance, negatives
        outside = ~torch.isin(self.indices, indices.cpu())
        extra = self.indices[outside]
        if not len(extra):
            return descriptors, relevance, negatives
        to_memory, to_memory_negative = (
            torch.from_numpy(block).to(relevance.device) for block in pairs.block(indices.cpu().numpy(), extra.numpy())
        )
        size, total = len(descriptors), len(descriptors) + len(extra)
        extended_relevance = relevance.new_zeros(total, total)
        extended_negatives = negatives.new_zeros(total, total)
        extended_relevance[:size, :size], extended_relevance[:size, size:] = relevance, to_memory
        extended_negatives[:size, :size], extended_negatives[:size, size:] = negatives, to_memory_negative
        remembered = self.descriptors[outside.to(self.descriptors.device)].to(descriptors)
        return torch.cat([descriptors, remembered]), extended_relevance, extended_negatives

    def write(self, descriptors: torch.Tensor, indices: torch.Tensor) -> None:
        """Remember the batch (detached), forgetting older copies of its images, then all but the
        newest ``size`` images."""
        indices = indices.cpu()
        unique = torch.from_numpy(np.unique(indices.numpy(), return_index=True)[1])  # an image twice in a batch: once
        new_indices, new_descriptors = indices[unique], descriptors.detach()[unique.to(descriptors.device)]
        if self.descriptors is None:
            self.indices, self.descriptors = new_indices, new_descriptors
        else:
            older = ~torch.isin(self.indices, new_indices)
            self.indices = torch.cat([self.indices[older], new_indices])
            self.descriptors = torch.cat([self.descriptors[older.to(self.descriptors.device)], new_descriptors])
        self.indices, self.descriptors = self.indices[-self.size :], self.descriptors[-self.size :]


class CrossBatchMemory(torch.nn.Module):
    """``loss`` with a cross-batch memory of the last ``size`` training images (``module.memory``,
    `DescriptorMemory`; 0: none, the loss of the batch alone): ``forward(descriptors, relevance,
    negatives, indices)`` ranks the batch's anchors against its images and the remembered ones
    outside it (their relevance read from the training ``pairs``), then remembers the batch.
    The module gives it the loss and the pairs."""

    def __init__(self, loss: Callable[..., torch.Tensor], pairs: TrainingPairs, *, size: int) -> None:
        super().__init__()
        require(size >= 0, "size", f"must be >= 0 (0: no memory), got {size}")
        self.loss = loss
        self.pairs = pairs
        self.memory = DescriptorMemory(size) if size else None

    def forward(
        self, descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor, indices: torch.Tensor
    ) -> torch.Tensor:
        if self.memory is None:
            return self.loss(descriptors, relevance, negatives)
        candidates, relevance, negatives = self.memory.extend(descriptors, relevance, negatives, indices, self.pairs)
        self.memory.write(descriptors, indices)
        return self.loss(candidates, relevance, negatives)
