"""Ranking losses against direct computations, ambiguity ignored, and each loss learning a toy task."""

import math

import numpy as np
import pytest
import torch
from pytorch_metric_learning.distances import CosineSimilarity

from locretrieval.training.losses import APLoss, ContrastiveLoss, ListwiseLoss, PerAnchorMean, TripletLoss

LOSSES = {"ap": APLoss, "triplet": TripletLoss, "contrastive": ContrastiveLoss, "listwise": ListwiseLoss}
#: The distance and reducer the pytorch-metric-learning losses are given (configs/loss/triplet.yaml's).
PML = {"distance": CosineSimilarity(), "reducer": PerAnchorMean()}

SETTINGS = [("ap", {"bins": 20}), ("triplet", {"margin": 0.1, "max_triplets_per_anchor": None, **PML}),
            ("triplet", {"margin": 0.1, "max_triplets_per_anchor": 2, **PML}),
            ("contrastive", {"pos_margin": 0.8, "neg_margin": 0.3, **PML}),
            ("listwise", {"temperature": 0.05, "target_temperature": 0.5})]  # fmt: skip
IDS = ["ap", "triplet", "triplet-hardest", "contrastive", "listwise"]


def unit(angles_deg) -> torch.Tensor:
    """2-D unit vectors (float32) at ``angles_deg``."""
    radians = torch.tensor(angles_deg, dtype=torch.float64) * math.pi / 180
    return torch.stack([torch.cos(radians), torch.sin(radians)], dim=1).float()


def exact_ap(scores: np.ndarray, labels: np.ndarray) -> float:
    """AP of ``labels`` ranked by decreasing ``scores``: mean precision at each positive."""
    hits = labels[np.argsort(-scores, kind="stable")]
    precision = np.cumsum(hits) / np.arange(1, len(hits) + 1)
    return float((precision * hits).sum() / hits.sum())


def toy_batch():
    """Anchor 0: relevance 2 to 1 and 1 to 2, negatives 3, 4. Anchor 1: relevant 0, negative 4,
    (1, 3) ambiguous. Image 2 has a relevant partner but no negative: not an anchor."""
    descriptors = unit([0.0, 20.0, 70.0, 40.0, 150.0])
    relevance = torch.zeros(5, 5)
    relevance[0, 1], relevance[0, 2], relevance[1, 0], relevance[2, 0] = 2.0, 1.0, 1.0, 1.0
    negatives = torch.zeros(5, 5, dtype=torch.bool)
    negatives[0, 3] = negatives[0, 4] = negatives[1, 4] = True
    return descriptors, relevance, negatives


ANCHORS = {0: ((1, 2), (3, 4)), 1: ((0,), (4,))}  # anchor: (positives, negatives) of toy_batch


def test_binned_ap_equals_exact_ap_when_similarities_sit_on_bin_centres():
    bins = 11  # centres 1.0, 0.8, ..., -1.0
    chosen = np.array([0.8, 0.4, 0.2, 0.0, -0.4, -0.8])  # one item per bin
    assert np.isin(np.round(chosen, 6), np.round(np.linspace(1.0, -1.0, bins), 6)).all()
    labels = np.array([1, 0, 1, 0, 1, 0], dtype=bool)
    descriptors = unit([0.0] + [math.degrees(math.acos(c)) for c in chosen])
    relevance = torch.zeros(7, 7)
    relevance[0, 1:] = torch.from_numpy(labels.astype(np.float32))
    negatives = torch.zeros(7, 7, dtype=torch.bool)
    negatives[0, 1:] = torch.from_numpy(~labels)
    loss = APLoss(bins)(descriptors, relevance, negatives)
    assert 1 - loss.item() == pytest.approx(exact_ap(chosen, labels), abs=1e-6)


def test_triplet_is_the_mean_hinge_per_anchor_then_over_anchors():
    descriptors, relevance, negatives = toy_batch()
    s = (descriptors @ descriptors.T).double().numpy()
    hinges = {a: [max(0.0, s[a, n] - s[a, p] + 0.1) for p in ps for n in ns] for a, (ps, ns) in ANCHORS.items()}
    expected = np.mean([np.mean(h) for h in hinges.values()])
    assert TripletLoss(0.1, max_triplets_per_anchor=None, **PML)(
        descriptors, relevance, negatives
    ).item() == pytest.approx(expected, abs=1e-6)
    hardest = np.mean([max(h) for h in hinges.values()])  # one triplet per anchor: its largest hinge
    assert TripletLoss(0.1, max_triplets_per_anchor=1, **PML)(
        descriptors, relevance, negatives
    ).item() == pytest.approx(hardest, abs=1e-6)


def test_contrastive_is_the_mean_positive_plus_negative_term_per_anchor():
    descriptors, relevance, negatives = toy_batch()
    s = (descriptors @ descriptors.T).double().numpy()
    per_anchor = [np.mean([max(0.0, 0.8 - s[a, p]) for p in ps]) + np.mean([max(0.0, s[a, n] - 0.3) for n in ns])
                  for a, (ps, ns) in ANCHORS.items()]  # fmt: skip
    loss = ContrastiveLoss(0.8, 0.3, **PML)
    assert loss(descriptors, relevance, negatives).item() == pytest.approx(np.mean(per_anchor), abs=1e-6)
    # a single pair of each kind (the library alone would return 0)
    single = torch.zeros(5, 5)
    single[0, 1] = 1.0
    expected = max(0.0, 0.8 - s[0, 1]) + max(0.0, s[0, 3] - 0.3)
    assert loss(descriptors, single, negatives & (torch.arange(5) == 3)).item() == pytest.approx(expected, abs=1e-6)


def test_listwise_is_the_cross_entropy_of_softmaxed_relevance_and_similarity():
    descriptors, relevance, negatives = toy_batch()
    s = (descriptors @ descriptors.T).double()
    cross_entropies = []
    for a, (ps, ns) in ANCHORS.items():
        candidates = list(ps + ns)
        target = torch.softmax(relevance[a, candidates].double() / 0.5, dim=0)
        cross_entropies.append(-(target * torch.log_softmax(s[a, candidates] / 0.05, dim=0)).sum().item())
    loss = ListwiseLoss(temperature=0.05, target_temperature=0.5)(descriptors, relevance, negatives)
    assert loss.item() == pytest.approx(np.mean(cross_entropies), rel=1e-5)


@pytest.mark.parametrize(("name", "settings"), SETTINGS, ids=IDS)
def test_ambiguous_pairs_and_non_anchors_change_no_loss(name, settings):
    loss = LOSSES[name](**settings)
    descriptors, relevance, negatives = toy_batch()
    pad = lambda m: torch.nn.functional.pad(m, (0, 1, 0, 1))  # noqa: E731  (image 5: ambiguous to all)
    relevance, negatives = pad(relevance), pad(negatives)
    with_ambiguous = torch.cat([descriptors, unit([10.0])])
    before = loss(with_ambiguous, relevance, negatives).item()
    moved = with_ambiguous.clone()
    moved[5] = unit([-30.0])[0]  # the ambiguous image moves: nothing changes
    assert loss(moved, relevance, negatives).item() == pytest.approx(before, abs=1e-6)
    moved[0] = unit([5.0])[0]  # the anchor moves: the loss changes
    assert loss(moved, relevance, negatives).item() != pytest.approx(before, abs=1e-6)


@pytest.mark.parametrize(("name", "settings"), SETTINGS, ids=IDS)
def test_no_anchor_gives_a_zero_with_a_gradient(name, settings):
    loss = LOSSES[name](**settings)
    descriptors, relevance, negatives = toy_batch()
    descriptors.requires_grad_(True)
    for no_anchor in [(torch.zeros(5, 5), negatives), (relevance, torch.zeros(5, 5, dtype=torch.bool))]:
        value = loss(descriptors, *no_anchor)
        assert value.item() == 0.0 and value.requires_grad
        value.backward()
        assert torch.equal(descriptors.grad, torch.zeros(5, 2))


@pytest.mark.parametrize(("name", "settings"), SETTINGS, ids=IDS)
def test_each_loss_learns_groups_of_relevant_images(name, settings):
    torch.manual_seed(0)
    groups = torch.arange(12) // 4
    relevance = (groups[:, None] == groups[None]).float()
    negatives = groups[:, None] != groups[None]
    parameters = torch.nn.Parameter(torch.randn(12, 8))
    loss = LOSSES[name](**settings)
    optimiser = torch.optim.Adam([parameters], lr=0.05)
    values = []
    for _ in range(100):
        value = loss(torch.nn.functional.normalize(parameters, dim=1), relevance, negatives)
        values.append(value.item())
        optimiser.zero_grad()
        value.backward()
        optimiser.step()
    descriptors = torch.nn.functional.normalize(parameters.detach(), dim=1)
    similarity = descriptors @ descriptors.T - 10 * torch.eye(12)
    assert values[-1] < values[0]
    assert (groups[similarity.argmax(1)] == groups).all()  # every nearest neighbour is relevant


def test_listwise_learns_the_graded_order():
    torch.manual_seed(1)
    relevance = torch.zeros(5, 5)
    relevance[0, 1:4] = torch.tensor([3.0, 2.0, 1.0])
    negatives = torch.zeros(5, 5, dtype=torch.bool)
    negatives[0, 4] = True
    parameters = torch.nn.Parameter(torch.randn(5, 4))
    optimiser = torch.optim.Adam([parameters], lr=0.05)
    loss = ListwiseLoss(temperature=0.1, target_temperature=1.0)
    for _ in range(200):
        value = loss(torch.nn.functional.normalize(parameters, dim=1), relevance, negatives)
        optimiser.zero_grad()
        value.backward()
        optimiser.step()
    descriptors = torch.nn.functional.normalize(parameters.detach(), dim=1)
    s = descriptors[0] @ descriptors[1:].T
    assert s[0] > s[1] > s[2] > s[3]


def test_shapes_and_settings_are_checked():
    with pytest.raises(ValueError, match=r"relevance and negatives \[B, B\] expected; got \(3, 2\), \(2, 2\)"):
        APLoss(10)(torch.zeros(3, 2), torch.zeros(2, 2), torch.zeros(2, 2, dtype=torch.bool))
    with pytest.raises(ValueError, match="bins"):
        APLoss(1)
    with pytest.raises(ValueError, match="max_triplets_per_anchor"):
        TripletLoss(0.1, max_triplets_per_anchor=0, **PML)
    with pytest.raises(ValueError, match="temperatures"):
        ListwiseLoss(0.1, 0.0)


def test_a_pytorch_metric_learning_loss_is_given_the_relevant_and_surely_unrelated_pairs():
    from pytorch_metric_learning.losses import MultiSimilarityLoss

    from locretrieval.training.losses import MetricLearningLoss

    given = []

    class Recording(MultiSimilarityLoss):
        def forward(self, embeddings, labels=None, indices_tuple=None, *args, **kwargs):
            given.append((labels, tuple(index.tolist() for index in indices_tuple)))
            return super().forward(embeddings, labels, indices_tuple, *args, **kwargs)

    torch.manual_seed(0)
    descriptors = torch.nn.functional.normalize(torch.randn(5, 8), dim=1).requires_grad_()
    relevance = torch.zeros(5, 5)
    relevance[0, 1] = relevance[1, 0] = 0.9
    relevance[2, 3] = 0.4  # graded, one-sided: a pair of the anchor 2 only
    negatives = torch.ones(5, 5, dtype=torch.bool)
    negatives[0, 2] = negatives[2, 0] = False  # ambiguous: neither
    loss = MetricLearningLoss(Recording(alpha=1.0, beta=50.0, base=0.0))(descriptors, relevance, negatives)
    loss.backward()
    labels, (a1, p, a2, n) = given[0]
    assert labels is None  # never class labels
    assert sorted(zip(a1, p)) == [(0, 1), (1, 0), (2, 3)]
    expected_negatives = {
        (a, b) for a in (0, 1, 2) for b in range(5) if a != b and relevance[a, b] == 0 and negatives[a, b]
    }
    assert set(zip(a2, n)) == expected_negatives  # anchors 3 and 4 have no relevant partner: not anchors
    assert descriptors.grad is not None and torch.isfinite(loss)
    # the same pairs through PML's own loss give the same value: the adapter adds nothing else
    direct = MultiSimilarityLoss(alpha=1.0, beta=50.0, base=0.0)(
        descriptors, None, (torch.tensor(a1), torch.tensor(p), torch.tensor(a2), torch.tensor(n))
    )
    assert float(direct) == pytest.approx(float(loss))
