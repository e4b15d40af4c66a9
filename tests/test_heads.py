"""Today's aggregation heads (MixVPR, SALAD, BoQ) and GeM over a spatial pyramid: the property
that defines each, their registry entries, and training through train.py."""

import math

import helpers
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from test_training import train_config

from locretrieval.models.heads import BoQHead, MixVPRHead, SALADHead
from locretrieval.models.networks import GeMPooling, build_pooling, build_retrieval_net, l2_normalize
from locretrieval.training.run import train


def test_mixvpr_mixes_a_fixed_grid_into_out_channels_times_out_rows():
    torch.manual_seed(0)
    head = MixVPRHead(32, grid=(7, 7), blocks=2, out_channels=12, out_rows=3).eval()
    features = torch.rand(3, 32, 14, 14)
    descriptors = head(features)
    assert descriptors.shape == (3, 36) and head.output_dim == 36
    torch.testing.assert_close(descriptors.norm(dim=1), torch.ones(3))
    # the same map at twice the resolution pools onto the same grid: the same descriptor
    torch.testing.assert_close(head(F.interpolate(features, scale_factor=2, mode="nearest")), descriptors)
    # each image is described on its own (no mixing across the batch)
    torch.testing.assert_close(head(features[1:2]), descriptors[1:2])


def test_salad_transport_plan_rows_and_columns_sum_to_their_marginals():
    torch.manual_seed(1)
    n, m = 6 * 5, 8
    head = SALADHead(16, clusters=m, cluster_dim=4, token_dim=6, hidden=32, iterations=200, regularization=0.5)
    plan = head.transport_plan(torch.randn(2, 16, 6, 5))
    assert plan.shape == (2, m + 1, n) and (plan >= 0).all()
    rows = torch.full((m + 1,), 1 / (n + m))
    rows[-1] = (n - m) / (n + m)  # the dustbin takes what the clusters do not
    torch.testing.assert_close(plan.sum(dim=2), rows.expand(2, -1), atol=1e-5, rtol=0)
    torch.testing.assert_close(plan.sum(dim=1), torch.full((2, n), 1 / (n + m)), atol=1e-6, rtol=0)
    # with SALAD's 3 iterations the columns (updated last) are exact: every feature is assigned in full
    few = SALADHead(16, clusters=m, cluster_dim=4, token_dim=6, hidden=32)
    few.load_state_dict(head.state_dict())
    assignment = few.transport_plan(torch.randn(2, 16, 6, 5)).sum(dim=1) * (n + m)
    torch.testing.assert_close(assignment, torch.ones(2, n), atol=1e-5, rtol=0)
    descriptors = head(torch.randn(2, 16, 6, 5))
    assert descriptors.shape == (2, m * 4 + 6) and head.output_dim == m * 4 + 6
    with pytest.raises(
        ValueError, match=r"SALAD needs more local features \(6 = H x W of the feature map\) than clusters \(8\)"
    ):
        head(torch.randn(1, 16, 3, 2))


@pytest.mark.parametrize(
    "head",
    [
        SALADHead(16, clusters=4, cluster_dim=4, token_dim=6, hidden=32),
        BoQHead(16, dim=16, queries=4, blocks=2, heads=2, rows=3),
    ],
    ids=["salad", "boq"],
)
def test_salad_and_boq_are_invariant_to_the_order_of_the_local_features(head):
    torch.manual_seed(2)
    head.eval()
    features = torch.randn(2, 16, 5, 4)
    shuffled = features.flatten(2)[:, :, torch.randperm(20)].reshape(2, 16, 4, 5)
    torch.testing.assert_close(head(shuffled), head(features), atol=1e-5, rtol=1e-5)


def test_boq_output_is_rows_times_dim_of_its_learned_queries():
    head = BoQHead(16, dim=16, queries=4, blocks=3, heads=2, rows=5)
    assert head(torch.randn(2, 16, 3, 3)).shape == (2, 80) and head.output_dim == 80
    assert sum(q.numel() for q in head.queries) == 3 * 4 * 16  # a bag of queries per block


def test_gem_pyramid_is_gem_of_each_grid_cell_with_every_level_weighing_the_same():
    torch.manual_seed(3)
    features = torch.rand(2, 3, 4, 6) * 2.0
    pooling, dimension = build_pooling(
        3, {"type": "gem_pyramid", "p": 3.0, "trainable": True, "levels": [[1, 1], [2, 3]]}
    )
    descriptors = pooling(features)
    assert dimension == 3 * (1 + 6) and descriptors.shape == (2, 21)
    power = features.numpy().astype("float64") ** 3
    whole = power.mean(axis=(2, 3)) ** (1 / 3)  # [B, C]
    cells = power.reshape(2, 3, 2, 2, 3, 2).mean(axis=(3, 5)) ** (
        1 / 3
    )  # 2 x 3 blocks of 2 x 2 pixels: [B, C, rows, cols]
    cells = cells.reshape(2, 3 * 6)  # cells fastest within a channel
    expected = [block / np.linalg.norm(block, axis=1, keepdims=True) for block in (whole, cells)]
    torch.testing.assert_close(descriptors.double(), torch.tensor(np.concatenate(expected, axis=1)))
    # the whole-image level alone is GeM's direction; the descriptor's norm is the square root of the number of levels
    single, _ = build_pooling(3, {"type": "gem_pyramid", "p": 3.0, "trainable": True, "levels": [[1, 1]]})
    torch.testing.assert_close(single(features), l2_normalize(GeMPooling(3.0)(features)))
    torch.testing.assert_close(descriptors.norm(dim=1), torch.full((2,), 2**0.5))
    default, dimension = build_pooling(
        3, {"type": "gem_pyramid", "p": 3.0, "trainable": True}
    )  # model.pooling.type=gem_pyramid
    assert default.levels == ((1, 1), (1, 3)) and dimension == 3 * 4
    with pytest.raises(ValueError, match=r"gem_pyramid levels must be \(rows, cols\) grids of at least 1 x 1"):
        build_pooling(3, {"type": "gem_pyramid", "p": 3.0, "trainable": True, "levels": [[0, 2]]})


def test_gem_pyramid_starts_from_the_pretrained_trunk_and_gems_initial_power():
    """``model=lite0_gem_pyramid``: no parameter is random (unlike a head), ``p`` from the config."""
    model = helpers.zoo_model("lite0_gem_pyramid")
    assert model.identity()["weights"]["random_parameters"] == []
    assert model.network.pooling.p.item() == 3.0 and model.network.output_dim == 1280 * 4
    assert model.architecture["pooling"] == {
        "type": "gem_pyramid",
        "p": 3.0,
        "trainable": True,
        "levels": [[1, 1], [1, 3]],
    }
    descriptors = model.network.eval()(torch.rand(2, 3, 96, 128))
    assert descriptors.shape == (2, 5120)


def test_a_head_ignores_another_types_options_and_refuses_unknown_ones():
    module, dimension = build_pooling(
        64, {"type": "mixvpr", "p": 3.0, "trainable": True, "out_rows": 2}
    )  # GeM's p, trainable
    assert isinstance(module, MixVPRHead) and dimension == 256 * 2
    with pytest.raises(ValueError, match=r"boq pooling: .*'bogus'"):
        build_pooling(64, {"type": "boq", "bogus": 1})
    network = build_retrieval_net("resnet18", {"type": "salad", "clusters": 4})
    assert network(torch.rand(1, 3, 128, 96)).shape == (1, network.output_dim) and not math.isnan(network.output_dim)


@pytest.mark.parametrize("head", ["mixvpr", "salad", "boq", "gem_pyramid"])
def test_train_py_trains_each_head(head, tmp_path):
    # a head starts from random weights (the trunk from ImageNet): model.random_init says so
    model = (
        ["model=lite0_gem_pyramid"]
        if head == "gem_pyramid"
        else [f"model.pooling.type={head}", "model.random_init=true"]
    )
    overrides = [*model, "+trainer.fast_dev_run=true", "paradigms.approximation.k=[1,3]"]
    if head == "salad":
        overrides.append("+model.pooling.clusters=4")  # 96 x 72 images: 3 x 2 local features of EfficientNet-Lite0
    validator = train(train_config(tmp_path, *overrides), tmp_path / "run")
    assert sorted({entry["epoch"] for entry in validator.history}) == [-1, 0]
    assert "val/approximation/ewb/k3/5m_10deg" in validator.history[-1]
