"""Ranking losses on a batch: ``loss(descriptors, relevance, negatives)``.

``descriptors``: L2-normalised ``[B, D]``; similarity is their dot product (cosine, in
[-1, 1]). ``relevance``: graded ``[B, B]`` (> 0: relevant, larger: more relevant; binary is
the 0/1 case). ``negatives``: boolean ``[B, B]``, pairs surely unrelated. Pairs that are
neither are ambiguous and no loss looks at them; the diagonal is never used. Each loss is
the mean over anchors (or tuples) that have what it needs, and 0 (with a gradient) when no
anchor has.
"""

from __future__ import annotations

import torch
from pytorch_metric_learning import distances, losses, reducers
from torch import nn


def _check(descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(positive, negative)`` boolean masks without the diagonal."""
    size = len(descriptors)
    if descriptors.ndim != 2 or relevance.shape != (size, size) or negatives.shape != (size, size):
        raise ValueError(f"descriptors [B, D], relevance and negatives [B, B] expected; got {tuple(descriptors.shape)}, "
                         f"{tuple(relevance.shape)} and {tuple(negatives.shape)}")
    off_diagonal = ~torch.eye(size, dtype=torch.bool, device=descriptors.device)
    positive = (relevance > 0) & off_diagonal
    return positive, negatives.bool() & off_diagonal & ~positive


def _zero(descriptors: torch.Tensor) -> torch.Tensor:
    return descriptors.sum() * 0.0


class APLoss(nn.Module):
    """1 - mAP, AP by histogram binning (Revaud et al., ICCV 2019): similarities are softly
    assigned to ``bins`` triangular kernels centred on ``1 = c_0 > c_1 > ... > c_{M-1} = -1``;
    per anchor, precision at bin m = positives / items in bins 0..m and the recall increment =
    positives in bin m / all positives, over its relevant and surely unrelated partners. Equal
    to the exact AP when every similarity sits on a bin centre, one item per bin."""

    def __init__(self, bins: int) -> None:
        super().__init__()
        if bins < 2:
            raise ValueError(f"bins must be >= 2, got {bins}")
        self.register_buffer("centres", torch.linspace(1.0, -1.0, bins), persistent=False)
        self.width = 2.0 / (bins - 1)

    def forward(self, descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor) -> torch.Tensor:
        positive, negative = _check(descriptors, relevance, negatives)
        anchors = positive.any(1) & negative.any(1)
        if not anchors.any():
            return _zero(descriptors)
        similarity = (descriptors @ descriptors.T)[anchors]
        candidates = (positive | negative)[anchors].float()
        labels = positive[anchors].float()
        assignment = (1 - (similarity[..., None] - self.centres).abs() / self.width).clamp(min=0) * candidates[..., None]
        positives_per_bin = (assignment * labels[..., None]).sum(1)
        items_per_bin = assignment.sum(1)
        precision = positives_per_bin.cumsum(1) / items_per_bin.cumsum(1).clamp(min=1e-12)
        recall = positives_per_bin / labels.sum(1, keepdim=True)
        return 1 - (precision * recall).sum(1).mean()


class TripletLoss(nn.Module):
    """pytorch-metric-learning's triplet margin loss on cosine similarity,
    ``max(0, s(a, n) - s(a, p) + margin)``, averaged over every triplet of the batch with p
    relevant to a and n surely unrelated to a (the triplets come from our relevance, not from
    class labels)."""

    def __init__(self, margin: float) -> None:
        super().__init__()
        self.loss = losses.TripletMarginLoss(margin=margin, distance=distances.CosineSimilarity(), reducer=reducers.MeanReducer())

    def forward(self, descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor) -> torch.Tensor:
        positive, negative = _check(descriptors, relevance, negatives)
        triplets = (positive[:, :, None] & negative[:, None, :]).nonzero(as_tuple=True)
        if not len(triplets[0]):
            return _zero(descriptors)
        return self.loss(descriptors, None, triplets)


class ContrastiveLoss(nn.Module):
    """pytorch-metric-learning's contrastive loss on cosine similarity: mean over relevant pairs
    of ``max(0, pos_margin - s)`` plus mean over surely unrelated pairs of ``max(0, s - neg_margin)``."""

    def __init__(self, pos_margin: float, neg_margin: float) -> None:
        super().__init__()
        self.loss = losses.ContrastiveLoss(
            pos_margin=pos_margin, neg_margin=neg_margin, distance=distances.CosineSimilarity(), reducer=reducers.MeanReducer()
        )

    def forward(self, descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor) -> torch.Tensor:
        positive, negative = _check(descriptors, relevance, negatives)
        anchors1, positives = positive.nonzero(as_tuple=True)
        anchors2, unrelated = negative.nonzero(as_tuple=True)
        if not len(anchors1) or not len(anchors2):
            return _zero(descriptors)
        pairs = (anchors1, positives, anchors2, unrelated)
        if all(len(x) == 1 for x in pairs):  # the library returns 0 for a single pair of each kind
            pairs = tuple(torch.cat([x, x]) for x in pairs)  # the same means, computed
        return self.loss(descriptors, None, pairs)


class ListwiseLoss(nn.Module):
    """ListNet top-one cross-entropy (Cao et al., ICML 2007) that learns the graded order: per
    anchor, over its relevant and surely unrelated partners, the target distribution is the
    relevance normalised to sum 1 (unrelated: 0) and the predicted one softmax(s / temperature);
    the loss is their cross-entropy, minimal when similarities order partners by relevance."""

    def __init__(self, temperature: float) -> None:
        super().__init__()
        if temperature <= 0:
            raise ValueError(f"temperature must be positive, got {temperature}")
        self.temperature = temperature

    def forward(self, descriptors: torch.Tensor, relevance: torch.Tensor, negatives: torch.Tensor) -> torch.Tensor:
        positive, negative = _check(descriptors, relevance, negatives)
        anchors = positive.any(1)
        if not anchors.any():
            return _zero(descriptors)
        candidates = (positive | negative)[anchors]
        target = torch.where(positive[anchors], relevance[anchors].float(), 0.0)
        target = target / target.sum(1, keepdim=True)
        logits = ((descriptors @ descriptors.T)[anchors] / self.temperature).masked_fill(~candidates, float("-inf"))
        log_predicted = torch.log_softmax(logits, dim=1)
        return -(target * log_predicted.masked_fill(~candidates, 0.0)).sum(1).mean()


#: Losses by config name (``loss=<name>``).
LOSSES = {"ap": APLoss, "triplet": TripletLoss, "contrastive": ContrastiveLoss, "listwise": ListwiseLoss}
