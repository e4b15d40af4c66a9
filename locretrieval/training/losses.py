"""Ranking losses on a batch: ``loss(descriptors, relevance, negatives)``.

``descriptors``: L2-normalised ``[B, D]``; similarity is their dot product (cosine, in
[-1, 1]). ``relevance``: graded ``[B, B]`` (> 0: relevant, larger: more relevant; binary is
the 0/1 case). ``negatives``: boolean ``[B, B]``, pairs surely unrelated (a pair marked both
counts as relevant). Pairs that are neither are ambiguous and no loss looks at them; the
diagonal is never used. Every loss is the mean over the anchors (rows) with at least one
relevant and one surely unrelated partner, and 0 (with a gradient) when no anchor has both.

The losses built on pytorch-metric-learning take its parts injected, as its own losses do: the
``distance`` (cosine similarity: the descriptors are unit vectors) and the ``reducer``
(`PerAnchorMean`, the mean per anchor above).
"""

from __future__ import annotations

import torch
from pytorch_metric_learning import losses
from pytorch_metric_learning.distances import BaseDistance
from pytorch_metric_learning.reducers import BaseReducer
from torch import nn


def _masks(
    descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(positive, negative)`` boolean ``[B, B]`` masks, the diagonal and anchors lacking either cleared."""
    size = len(descriptors)
    if descriptors.ndim != 2 or relevance.shape != (size, size) or negatives.shape != (size, size):
        raise ValueError(f"descriptors [B, D], relevance and negatives [B, B] expected; "
                         f"got {tuple(descriptors.shape)}, "
                         f"{tuple(relevance.shape)} and {tuple(negatives.shape)}")  # fmt: skip
    off_diagonal = ~torch.eye(size, dtype=torch.bool, device=descriptors.device)
    positive = (relevance > 0) & off_diagonal
    negative = negatives.bool() & off_diagonal & ~positive
    anchors = (positive.any(1) & negative.any(1))[:, None]
    return positive & anchors, negative & anchors


def _zero(descriptors: torch.Tensor) -> torch.Tensor:
    return descriptors.sum() * 0.0


def _mean_per_anchor(values: torch.Tensor, anchors: torch.Tensor, size: int) -> torch.Tensor:
    """Mean over anchors of the mean of each anchor's ``values`` (``anchors``: their row)."""
    counts = torch.bincount(anchors, minlength=size)
    sums = torch.zeros(size, dtype=values.dtype, device=values.device).index_add(0, anchors, values)
    present = counts > 0
    return (sums[present] / counts[present]).mean()


class PerAnchorMean(BaseReducer):
    """A pytorch-metric-learning reducer: the mean over anchors of the mean of each anchor's
    triplet or pair losses (the anchor: the first index of each), so that an anchor with many
    partners weighs as much as one with few. A loss of several kinds of pairs (contrastive: its
    relevant and unrelated pairs) sums their reductions."""

    def _reduce(
        self, losses: torch.Tensor, loss_indices: tuple[torch.Tensor, ...], embeddings: torch.Tensor, labels: None
    ) -> torch.Tensor:
        return _mean_per_anchor(losses, loss_indices[0], len(embeddings))

    triplet_reduction = pos_pair_reduction = neg_pair_reduction = _reduce


class APLoss(nn.Module):
    """1 - mAP, AP by histogram binning (Revaud et al., ICCV 2019): similarities are softly
    assigned to ``bins`` triangular kernels centred on ``1 = c_0 > c_1 > ... > c_{bins-1} = -1``
    (width: the spacing); per anchor, over its relevant and surely unrelated partners,
    precision at bin m = positives / items in bins 0..m and the recall increment = positives
    in bin m / all positives; AP = sum of their products. Equal to the exact AP when every
    similarity sits on a bin centre and no bin holds items of both labels."""

    def __init__(self, bins: int) -> None:
        super().__init__()
        if bins < 2:
            raise ValueError(f"bins must be >= 2, got {bins}")
        self.register_buffer("centres", torch.linspace(1.0, -1.0, bins), persistent=False)
        self.width = 2.0 / (bins - 1)

    def forward(self, descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor) -> torch.Tensor:
        positive, negative = _masks(descriptors, relevance, negatives)
        anchors = positive.any(1)
        if not anchors.any():
            return _zero(descriptors)
        similarity = (descriptors @ descriptors.T)[anchors]
        candidates = (positive | negative)[anchors].to(similarity.dtype)
        labels = positive[anchors].to(similarity.dtype)
        kernel = (1 - (similarity[..., None] - self.centres).abs() / self.width).clamp(min=0)
        assignment = kernel * candidates[..., None]  # [anchors, B, bins]
        positives_per_bin = (assignment * labels[..., None]).sum(1)
        precision = positives_per_bin.cumsum(1) / assignment.sum(1).cumsum(1).clamp(min=1e-12)
        recall = positives_per_bin / labels.sum(1, keepdim=True)
        return 1 - (precision * recall).sum(1).mean()


class TripletLoss(nn.Module):
    """pytorch-metric-learning's ``TripletMarginLoss`` on cosine similarity,
    ``max(0, s(a, n) - s(a, p) + margin)``, over triplets with p relevant to a and n surely
    unrelated to a, given to it as ``indices_tuple`` (never class labels: PML 2.x accepts
    ``labels=None`` with an ``indices_tuple``). Mean over each anchor's triplets, then over
    anchors. ``max_triplets_per_anchor``: ``None`` keeps every triplet; a number keeps each
    anchor's hardest ones (largest ``s(a, n) - s(a, p)`` by the ``distance``, chosen without
    gradient, ties by index), a deterministic choice. ``distance`` and ``reducer``: the PML loss's
    (``distance``, e.g. ``CosineSimilarity``; ``reducer``, e.g. `PerAnchorMean`)."""

    def __init__(
        self, margin: float, max_triplets_per_anchor: int | None, distance: BaseDistance, reducer: BaseReducer
    ) -> None:
        super().__init__()
        if max_triplets_per_anchor is not None and max_triplets_per_anchor < 1:
            raise ValueError(f"max_triplets_per_anchor must be >= 1 or None, got {max_triplets_per_anchor}")
        self.max_triplets_per_anchor = max_triplets_per_anchor
        self.loss = losses.TripletMarginLoss(margin=margin, distance=distance, reducer=reducer)

    def forward(self, descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor) -> torch.Tensor:
        positive, negative = _masks(descriptors, relevance, negatives)
        rows = positive.any(1).nonzero(as_tuple=True)[0]  # the anchors only: [a, p, n] grows with the cube of B
        if not len(rows):
            return _zero(descriptors)
        valid = positive[rows, :, None] & negative[rows, None, :]  # [a, p, n]
        anchors, positives, unrelated = self._select(descriptors, rows, valid)
        return self.loss(descriptors, None, (rows[anchors], positives, unrelated))

    def _select(self, descriptors: torch.Tensor, rows: torch.Tensor, valid: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``(anchors, positives, negatives)``, anchors as positions in ``rows``: every valid triplet
        or each anchor's hardest."""
        if self.max_triplets_per_anchor is None:
            return valid.nonzero(as_tuple=True)
        size = len(descriptors)
        with torch.no_grad():
            distance = self.loss.distance
            similarity = distance(descriptors[rows], descriptors) * (1 if distance.is_inverted else -1)
            violation = (similarity[:, None, :] - similarity[:, :, None]).masked_fill(~valid, float("-inf"))
            keep = min(self.max_triplets_per_anchor, size * size)
            order = torch.sort(violation.view(len(rows), -1), dim=1, descending=True, stable=True).indices[:, :keep]
        chosen = torch.zeros_like(valid).view(len(rows), -1).scatter_(1, order, True).view_as(valid)
        return (chosen & valid).nonzero(as_tuple=True)


class ContrastiveLoss(nn.Module):
    """pytorch-metric-learning's ``ContrastiveLoss`` on cosine similarity, given the pairs as
    ``indices_tuple`` ``(a1, p, a2, n)`` (never class labels): per anchor, the mean over its
    relevant partners of ``max(0, pos_margin - s)`` plus the mean over its surely unrelated
    ones of ``max(0, s - neg_margin)``; mean over anchors (by the ``reducer``, e.g. `PerAnchorMean`;
    ``distance``: the PML loss's, e.g. ``CosineSimilarity``)."""

    def __init__(self, pos_margin: float, neg_margin: float, distance: BaseDistance, reducer: BaseReducer) -> None:
        super().__init__()
        self.loss = losses.ContrastiveLoss(
            pos_margin=pos_margin, neg_margin=neg_margin, distance=distance, reducer=reducer
        )

    def forward(self, descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor) -> torch.Tensor:
        positive, negative = _masks(descriptors, relevance, negatives)
        if not positive.any():
            return _zero(descriptors)
        pairs = positive.nonzero(as_tuple=True) + negative.nonzero(as_tuple=True)
        if all(len(x) == 1 for x in pairs):  # PML returns 0 for a single pair of each kind:
            pairs = tuple(torch.cat([x, x]) for x in pairs)  # duplicated, the means are the same
        return self.loss(descriptors, None, pairs)


class MetricLearningLoss(nn.Module):
    """Any pytorch-metric-learning loss (``loss``, e.g. ``MultiSimilarityLoss``, the field's VPR
    recipes' loss) on the batch's pairs: every relevant pair as a positive and every surely
    unrelated pair as a negative (the project's negatives rule, `train_relevance.negatives`),
    given to it as ``indices_tuple`` ``(a1, p, a2, n)``, never as class labels (graded relevance
    is no partition into classes). Its own reducer and distance apply (cosine similarity by
    default for most; the descriptors are unit vectors)."""

    def __init__(self, loss: nn.Module) -> None:
        super().__init__()
        self.loss = loss

    def forward(self, descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor) -> torch.Tensor:
        positive, negative = _masks(descriptors, relevance, negatives)
        if not positive.any():
            return _zero(descriptors)
        return self.loss(descriptors, None, positive.nonzero(as_tuple=True) + negative.nonzero(as_tuple=True))


class ListwiseLoss(nn.Module):
    """ListNet top-one cross-entropy (Cao et al., ICML 2007) that learns the graded order: per
    anchor, over its candidates (relevant and surely unrelated partners, relevance 0 for the
    latter), the target is ``softmax(relevance / target_temperature)`` and the prediction
    ``softmax(s / temperature)``; the loss is their cross-entropy, lowest when similarities
    order candidates by relevance. A small ``target_temperature`` (against the relevance
    gaps) leaves little target mass on unrelated and barely relevant partners."""

    def __init__(self, temperature: float, target_temperature: float) -> None:
        super().__init__()
        if temperature <= 0 or target_temperature <= 0:
            raise ValueError(f"temperatures must be positive, got {temperature} and {target_temperature}")
        self.temperature, self.target_temperature = temperature, target_temperature

    def forward(self, descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor) -> torch.Tensor:
        positive, negative = _masks(descriptors, relevance, negatives)
        anchors = positive.any(1)
        if not anchors.any():
            return _zero(descriptors)
        excluded = ~(positive | negative)[anchors]
        similarity = (descriptors @ descriptors.T)[anchors]
        graded = torch.where(positive[anchors], relevance[anchors].to(similarity.dtype), 0.0)
        target = torch.softmax((graded / self.target_temperature).masked_fill(excluded, float("-inf")), dim=1)
        log_predicted = torch.log_softmax((similarity / self.temperature).masked_fill(excluded, float("-inf")), dim=1)
        return -(target * log_predicted.masked_fill(excluded, 0.0)).sum(1).mean()
