"""Ranking losses against direct computations, ambiguity ignored, and each loss learning a toy task."""

import math

import numpy as np
import pytest
import torch

from locretrieval.training.losses import LOSSES, APLoss, ContrastiveLoss, ListwiseLoss, TripletLoss

SETTINGS = {"ap": {"bins": 20}, "triplet": {"margin": 0.1}, "contrastive": {"pos_margin": 0.8, "neg_margin": 0.3},
            "listwise": {"temperature": 0.05}}  # fmt: skip


def unit(angles_deg) -> torch.Tensor:
    """2-D unit vectors at ``angles_deg``."""
    radians = torch.tensor(angles_deg, dtype=torch.float64) * math.pi / 180
    return torch.stack([torch.cos(radians), torch.sin(radians)], dim=1)


def exact_ap(scores: np.ndarray, labels: np.ndarray) -> float:
    order = np.argsort(-scores, kind="stable")
    hits = labels[order]
    precision = np.cumsum(hits) / np.arange(1, len(hits) + 1)
    return float((precision * hits).sum() / hits.sum())


def test_binned_ap_equals_exact_ap_when_similarities_sit_on_bin_centres():
    bins = 11  # centres 1.0, 0.8, ..., -1.0
    centres = np.linspace(1.0, -1.0, bins)
    chosen = [0.8, 0.4, 0.2, 0.0, -0.4, -0.8]  # one item per bin
    angles = [0.0] + [math.degrees(math.acos(c)) for c in chosen]
    descriptors = unit(angles).float()
    labels = np.array([1, 0, 1, 0, 1, 0], dtype=bool)
    relevance = torch.zeros(7, 7)
    relevance[0, 1:] = torch.from_numpy(labels.astype(np.float32))
    negatives = torch.zeros(7, 7, dtype=torch.bool)
    negatives[0, 1:] = torch.from_numpy(~labels)
    assert set(np.round(chosen, 6)) <= set(np.round(centres, 6))
    loss = APLoss(bins)(descriptors, relevance, negatives)
    assert 1 - loss.item() == pytest.approx(exact_ap(np.array(chosen), labels), abs=1e-6)


def toy_batch():
    """Anchor 0 with positives 1, 2 and negatives 3, 4; pair (1, 3) ambiguous."""
    descriptors = unit([0.0, 20.0, 70.0, 40.0, 150.0]).float()
    relevance = torch.zeros(5, 5)
    relevance[0, 1], relevance[0, 2] = 2.0, 1.0
    negatives = torch.zeros(5, 5, dtype=torch.bool)
    negatives[0, 3] = negatives[0, 4] = True
    return descriptors, relevance, negatives


def test_triplet_and_contrastive_equal_their_hand_computed_values():
    descriptors, relevance, negatives = toy_batch()
    s = (descriptors @ descriptors.T).double()
    triplets = [(p, n) for p in (1, 2) for n in (3, 4)]
    expected = np.mean([max(0.0, s[0, n] - s[0, p] + 0.1) for p, n in triplets])
    assert TripletLoss(0.1)(descriptors, relevance, negatives).item() == pytest.approx(expected, abs=1e-6)
    positive_part = np.mean([max(0.0, 0.8 - s[0, p]) for p in (1, 2)])
    negative_part = np.mean([max(0.0, s[0, n] - 0.3) for n in (3, 4)])
    contrastive = ContrastiveLoss(0.8, 0.3)(descriptors, relevance, negatives).item()
    assert contrastive == pytest.approx(positive_part + negative_part, abs=1e-6)
    # a single pair of each kind (the library alone would return 0)
    one = ContrastiveLoss(0.8, 0.3)(descriptors, relevance * (relevance == 2), negatives & (torch.arange(5) == 3))
    assert one.item() == pytest.approx(max(0, 0.8 - s[0, 1].item()) + max(0, s[0, 3].item() - 0.3), abs=1e-6)


def test_listwise_equals_the_hand_computed_cross_entropy():
    descriptors, relevance, negatives = toy_batch()
    s = (descriptors @ descriptors.T).double()[0, 1:] / 0.05
    predicted = torch.log_softmax(s, dim=0)
    target = torch.tensor([2.0, 1.0, 0.0, 0.0], dtype=torch.float64) / 3
    expected = -(target * predicted).sum().item()
    assert ListwiseLoss(0.05)(descriptors, relevance, negatives).item() == pytest.approx(expected, rel=1e-5)


@pytest.mark.parametrize("name", sorted(LOSSES))
def test_ambiguous_pairs_change_no_loss_and_no_anchor_gives_zero(name):
    loss = LOSSES[name](**SETTINGS[name])
    descriptors, relevance, negatives = toy_batch()
    pad = lambda m: torch.nn.functional.pad(m, (0, 1, 0, 1))  # noqa: E731  (image 5: ambiguous to anchor 0)
    relevance, negatives = pad(relevance), pad(negatives)
    with_ambiguous = torch.cat([descriptors, unit([10.0]).float()])
    before = loss(with_ambiguous, relevance, negatives).item()
    moved = with_ambiguous.clone()
    moved[5] = unit([-30.0])[0].float()  # the ambiguous image moves: nothing changes
    assert loss(moved, relevance, negatives).item() == pytest.approx(before, abs=1e-6)
    moved[0] = unit([5.0])[0].float()  # the anchor moves: the loss changes
    assert loss(moved, relevance, negatives).item() != pytest.approx(before, abs=1e-6)
    assert loss(with_ambiguous, torch.zeros(6, 6), negatives).item() == 0.0  # no positive: no anchor


@pytest.mark.parametrize("name", sorted(LOSSES))
def test_each_loss_learns_groups_of_relevant_images(name):
    torch.manual_seed(0)
    groups = torch.arange(12) // 4
    relevance = (groups[:, None] == groups[None]).float()
    negatives = groups[:, None] != groups[None]
    parameters = torch.nn.Parameter(torch.randn(12, 8))
    loss = LOSSES[name](**SETTINGS[name])
    optimiser = torch.optim.Adam([parameters], lr=0.05)
    first = None
    for _ in range(150):
        value = loss(torch.nn.functional.normalize(parameters, dim=1), relevance, negatives)
        first = value.item() if first is None else first
        optimiser.zero_grad()
        value.backward()
        optimiser.step()
    descriptors = torch.nn.functional.normalize(parameters.detach(), dim=1)
    similarity = descriptors @ descriptors.T - 10 * torch.eye(12)
    assert value.item() < first
    assert (groups[similarity.argmax(1)] == groups).all()  # every nearest neighbour is relevant


def test_listwise_learns_the_graded_order():
    torch.manual_seed(1)
    relevance = torch.zeros(5, 5)
    relevance[0, 1:4] = torch.tensor([3.0, 2.0, 1.0])
    negatives = torch.zeros(5, 5, dtype=torch.bool)
    negatives[0, 4] = True
    parameters = torch.nn.Parameter(torch.randn(5, 4))
    optimiser = torch.optim.Adam([parameters], lr=0.05)
    loss = ListwiseLoss(0.1)
    for _ in range(300):
        value = loss(torch.nn.functional.normalize(parameters, dim=1), relevance, negatives)
        optimiser.zero_grad()
        value.backward()
        optimiser.step()
    descriptors = torch.nn.functional.normalize(parameters.detach(), dim=1)
    s = descriptors[0] @ descriptors[1:].T
    assert s[0] > s[1] > s[2] > s[3]


def test_shapes_are_checked():
    with pytest.raises(ValueError, match=r"relevance and negatives \[B, B\] expected; got \(3, 2\), \(2, 2\)"):
        APLoss(10)(torch.zeros(3, 2), torch.zeros(2, 2), torch.zeros(2, 2, dtype=torch.bool))
