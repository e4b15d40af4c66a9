"""Today's aggregation heads (MixVPR, SALAD, BoQ) and GeM over a spatial pyramid: the property
that defines each, their configs in ``configs/model/pooling/``, a pooling from outside the package,
and training through train.py."""

import math
from dataclasses import asdict

import helpers
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from helpers import train
from omegaconf import OmegaConf
from training_runs import SMALL_VALIDATION, train_config

from locretrieval.models.files.weights import save_checkpoint
from locretrieval.models.networks import (
    GeMPooling,
    build_pooling,
    build_retrieval_net,
    l2_normalize,
    pooling_settings,
    upgrade_legacy_pooling,
)
from locretrieval.models.trainable.backbones import TorchvisionBackbone
from locretrieval.models.trainable.heads import BoQHead, MixVPRHead, SALADHead

RESNET18 = TorchvisionBackbone("resnet18")
#: SALAD's options but the sizes (those of configs/model/pooling/salad.yaml).
SALAD_OPTIONS = {"hidden": 32, "iterations": 3, "regularization": 1.0, "token": "mean", "dropout": 0.0}


def configured_pooling(name: str, **options) -> dict:
    """The settings of ``configs/model/pooling/<name>.yaml``, its options overridden by ``options``."""
    node = OmegaConf.load(helpers.CONFIGS / "model" / "pooling" / f"{name}.yaml")
    return pooling_settings({**OmegaConf.to_container(node), **options})


def test_mixvpr_mixes_a_fixed_grid_into_out_channels_times_out_rows():
    torch.manual_seed(0)
    head = MixVPRHead(32, grid=(7, 7), blocks=2, mlp_ratio=1, out_channels=12, out_rows=3).eval()
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
    head = SALADHead(
        16, clusters=m, cluster_dim=4, token_dim=6, **{**SALAD_OPTIONS, "iterations": 200, "regularization": 0.5}
    )
    plan = head.transport_plan(torch.randn(2, 16, 6, 5))
    assert plan.shape == (2, m + 1, n) and (plan >= 0).all()
    rows = torch.full((m + 1,), 1 / (n + m))
    rows[-1] = (n - m) / (n + m)  # the dustbin takes what the clusters do not
    torch.testing.assert_close(plan.sum(dim=2), rows.expand(2, -1), atol=1e-5, rtol=0)
    torch.testing.assert_close(plan.sum(dim=1), torch.full((2, n), 1 / (n + m)), atol=1e-6, rtol=0)
    # with SALAD's 3 iterations the columns (updated last) are exact: every feature is assigned in full
    few = SALADHead(16, clusters=m, cluster_dim=4, token_dim=6, **SALAD_OPTIONS)
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
        SALADHead(16, clusters=4, cluster_dim=4, token_dim=6, **SALAD_OPTIONS),
        BoQHead(16, dim=16, queries=4, blocks=2, heads=2, rows=3, input_kernel=1),
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
    head = BoQHead(16, dim=16, queries=4, blocks=3, heads=2, rows=5, input_kernel=1)
    assert head(torch.randn(2, 16, 3, 3)).shape == (2, 80) and head.output_dim == 80
    assert sum(q.numel() for q in head.queries) == 3 * 4 * 16  # a bag of queries per block


def test_gem_pyramid_is_gem_of_each_grid_cell_with_every_level_weighing_the_same():
    torch.manual_seed(3)
    features = torch.rand(2, 3, 4, 6) * 2.0
    pooling = build_pooling(3, configured_pooling("gem_pyramid", levels=[[1, 1], [2, 3]]))
    descriptors = pooling(features)
    assert pooling.output_dim == 3 * (1 + 6) and descriptors.shape == (2, 21)
    power = features.numpy().astype("float64") ** 3
    whole = power.mean(axis=(2, 3)) ** (1 / 3)  # [B, C]
    cells = power.reshape(2, 3, 2, 2, 3, 2).mean(axis=(3, 5)) ** (
        1 / 3
    )  # 2 x 3 blocks of 2 x 2 pixels: [B, C, rows, cols]
    cells = cells.reshape(2, 3 * 6)  # cells fastest within a channel
    expected = [block / np.linalg.norm(block, axis=1, keepdims=True) for block in (whole, cells)]
    torch.testing.assert_close(descriptors.double(), torch.tensor(np.concatenate(expected, axis=1)))
    # the whole-image level alone is GeM's direction; the descriptor's norm is the square root of the number of levels
    single = build_pooling(3, configured_pooling("gem_pyramid", levels=[[1, 1]]))
    torch.testing.assert_close(single(features), l2_normalize(GeMPooling(3, 3.0, trainable=True)(features)))
    torch.testing.assert_close(descriptors.norm(dim=1), torch.full((2,), 2**0.5))
    default = build_pooling(3, configured_pooling("gem_pyramid"))  # model/pooling=gem_pyramid
    assert default.levels == ((1, 1), (1, 3)) and default.output_dim == 3 * 4
    with pytest.raises(ValueError, match=r"gem_pyramid levels must be \(rows, cols\) grids of at least 1 x 1"):
        build_pooling(3, configured_pooling("gem_pyramid", levels=[[0, 2]]))


def test_gem_pyramid_starts_from_the_pretrained_trunk_and_gems_initial_power():
    """``model=lite0_gem_pyramid``: no parameter is random (unlike a head), ``p`` from the config."""
    model = helpers.zoo_model("lite0_gem_pyramid")
    assert model.identity()["weights"]["random_parameters"] == []
    assert model.network.pooling.p.item() == 3.0 and model.network.output_dim == 1280 * 4
    assert model.architecture["pooling"] == {
        "_target_": "locretrieval.models.networks.SpatialPyramidGeM",
        "p": 3.0,
        "trainable": True,
        "levels": [[1, 1], [1, 3]],
    }
    descriptors = model.network.eval()(torch.rand(2, 3, 96, 128))
    assert descriptors.shape == (2, 5120)


def test_a_pooling_refuses_options_it_does_not_take_or_lacks_naming_them():
    module = build_pooling(64, configured_pooling("mixvpr", out_rows=2))
    assert isinstance(module, MixVPRHead) and module.output_dim == 256 * 2
    with pytest.raises(ValueError, match=r"model.pooling \(locretrieval.models.trainable.heads.BoQHead\): .*'bogus'"):
        configured_pooling("boq", bogus=1)
    with pytest.raises(ValueError, match=r"model.pooling \(.*MixVPRHead\): .*'p'.*it takes \['grid', 'blocks'"):
        configured_pooling("mixvpr", p=3.0)  # GeM's option on another head: refused, not ignored
    with pytest.raises(ValueError, match=r"model.pooling \(.*NetVLADPooling\): missing .*'clusters'"):
        pooling_settings({"_target_": "locretrieval.models.networks.NetVLADPooling"})
    network = build_retrieval_net(RESNET18, configured_pooling("salad", clusters=4))
    assert network(torch.rand(1, 3, 128, 96)).shape == (1, network.output_dim) and not math.isnan(network.output_dim)


def test_model_pooling_switches_the_head_with_its_own_options_and_refuses_anothers():
    config = helpers.evaluate_config("model=gem", "model/pooling=boq")
    assert (
        config.model.pooling._target_ == "locretrieval.models.trainable.heads.BoQHead"
        and "p" not in config.model.pooling
    )
    boq = helpers.zoo_model("gem", pooling=config.model.pooling, random_init=True, backbone=RESNET18)
    assert isinstance(boq.network.pooling, BoQHead) and boq.network.output_dim == 128 * 8
    with pytest.raises(ValueError, match=r"BoQHead\): got an unexpected keyword argument 'p'"):
        helpers.zoo_model("gem", pooling={**config.model.pooling, "p": 3.0}, random_init=True, backbone=RESNET18)


class MaxPooling(torch.nn.Module):
    """A pooling from outside the package: the maximum over the map, times ``scale``."""

    def __init__(self, channels: int, scale: float) -> None:
        super().__init__()
        self.scale, self.output_dim = scale, channels

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return features.amax(dim=(2, 3)) * self.scale


def test_a_pooling_from_outside_the_package_is_one_class_and_one_yaml(tmp_path, monkeypatch):
    """A test module's class, chosen by a YAML in a config folder of the user's (hydra.searchpath)."""
    folder = tmp_path / "configs" / "model" / "pooling"
    folder.mkdir(parents=True)
    (folder / "max.yaml").write_text(f"_target_: {__name__}.MaxPooling\n_partial_: true\nscale: 2.0\n")
    config = helpers.evaluate_config(
        f"hydra.searchpath=[file://{tmp_path / 'configs'}]", "model=gem", "model/pooling=max"
    )
    model = helpers.zoo_model("gem", pooling=config.model.pooling, random_init=True, backbone=RESNET18)
    assert model.architecture["pooling"] == {"_target_": f"{__name__}.MaxPooling", "scale": 2.0}
    images = torch.rand(2, 3, 64, 96)
    torch.testing.assert_close(
        model.network.eval()(images), l2_normalize(model.network.backbone(images).amax(dim=(2, 3)))
    )
    assert model.network.output_dim == 512


def test_a_checkpoint_of_0_11_reads_with_its_pooling_record_upgraded(tmp_path):
    """0.11.0 recorded the pooling as ``{type: ..., options as configured}`` and the backbone as a name;
    today's settings name the classes."""
    assert upgrade_legacy_pooling({"type": "gem", "p": 3.0, "trainable": True}) == configured_pooling("gem")
    assert upgrade_legacy_pooling({"type": "mixvpr", "p": 3.0, "trainable": True}) == configured_pooling("mixvpr")
    assert upgrade_legacy_pooling({"type": "salad", "clusters": 4}) == configured_pooling("salad", clusters=4)
    model = helpers.zoo_model("gem", random_init=True, backbone=RESNET18)
    path = tmp_path / "legacy.pt"
    architecture = {
        **model.architecture,
        "backbone": "resnet18",
        "pooling": {"type": "gem", "p": 3.0, "trainable": True},
    }
    save_checkpoint(path, "trainable", architecture, asdict(model.preprocessing), model.network.state_dict())
    loaded = helpers.zoo_model("gem", weights=path, backbone=RESNET18)
    assert loaded.architecture == model.architecture
    torch.testing.assert_close(loaded.network.state_dict(), model.network.state_dict())


@pytest.mark.parametrize("head", ["mixvpr", "salad", "boq", "gem_pyramid"])
def test_train_py_trains_each_head(head, tmp_path):
    # a head starts from random weights (the trunk from ImageNet): model.random_init says so
    model = (
        ["model=lite0_gem_pyramid"] if head == "gem_pyramid" else [f"model/pooling={head}", "model.random_init=true"]
    )
    overrides = [*model, "+trainer.fast_dev_run=true", "paradigms.approximation.k=[1,3]", *SMALL_VALIDATION]
    if head == "salad":
        overrides.append("model.pooling.clusters=4")  # 96 x 72 images: 3 x 2 local features of EfficientNet-Lite0
    validator = train(train_config(tmp_path, *overrides), tmp_path / "run")
    assert sorted({entry["epoch"] for entry in validator.history}) == [-1, 0]
    assert "val/approximation/ewb/k3/5m_10deg" in validator.history[-1]
