"""The Lightning module (`locretrieval.training.module`): train.py finetune=<preset> (the field's
descriptors fine-tuned with their authors' recipes: their own preprocessing, the parts they keep
fixed, their optimizer), each taking training steps; a learning rate per part of any network
(module.lr_scales); frozen batch norm and parameters; a diverging run stopped; a loss's parameters optimized."""

import re

import helpers
import numpy as np
import pytest
import torch
from helpers import train
from hydra.utils import instantiate
from training_runs import SMALL_VALIDATION, train_config

from locretrieval.config import ConfigError, SettingError
from locretrieval.models.files.weights import embedded_checkpoint, load_torch_file
from locretrieval.models.networks import GeMPooling, RetrievalNet
from locretrieval.training.module import freeze_parameters

#: CosPlace's and EigenPlaces' hub module as their code lays it out (torchvision ResNet children as
#: ``backbone``; L2, GeM, flatten, linear, L2 as ``aggregation``), random weights: the published
#: entry point would fetch its weights, which cannot happen here.
GEOLOCALIZATION_HUBCONF = """dependencies = ["torch", "torchvision"]
import torch
import torch.nn.functional as F
import torchvision
from torch import nn


class L2Norm(nn.Module):
    def forward(self, x):
        return F.normalize(x, p=2.0, dim=1)


class GeM(nn.Module):
    def __init__(self, p=3, eps=1e-6):
        super().__init__()
        self.p = nn.Parameter(torch.ones(1) * p)
        self.eps = eps

    def forward(self, x):
        return F.avg_pool2d(x.clamp(min=self.eps).pow(self.p), (x.size(-2), x.size(-1))).pow(1.0 / self.p)


class Flatten(nn.Module):
    def forward(self, x):
        return x[:, :, 0, 0]


class GeoLocalizationNet(nn.Module):
    def __init__(self, backbone, fc_output_dim):
        super().__init__()
        resnet = getattr(torchvision.models, backbone.lower())(weights=None)
        self.backbone = nn.Sequential(*list(resnet.children())[:-2])
        features_dim = 512 if backbone in ("ResNet18", "ResNet34") else 2048
        self.aggregation = nn.Sequential(L2Norm(), GeM(), Flatten(), nn.Linear(features_dim, fc_output_dim), L2Norm())

    def forward(self, x):
        return self.aggregation(self.backbone(x))


def get_trained_model(backbone="ResNet50", fc_output_dim=2048):
    torch.manual_seed(0)
    return GeoLocalizationNet(backbone, fc_output_dim)
"""
#: preset -> (the hub repository's cache folder or None, overrides that make one step cheap here).
PRESETS = {
    "salad": (None, ("model.random_init=true",)),
    "boq": (None, ("model.random_init=true",)),
    "megaloc": (None, ("model.random_init=true",)),
    "cosplace": ("gmberton_cosplace_main", ("model.kwargs={backbone: ResNet18, fc_output_dim: 32}",)),
    "eigenplaces": ("gmberton_eigenplaces_main", ("model.kwargs={backbone: ResNet18, fc_output_dim: 32}",)),
}
#: preset -> overrides that shrink its head for the training step: MegaLoc's whitening holds 16,640 x 8,448 weights.
SMALL_HEADS = {"megaloc": ("model.whiten_dim=256",)}
#: The fine-tuning runs' data: `SMALL_VALIDATION` (each validation describes every image with the
#: preset's network, a ViT-B for three of them) and a step of 5 images (2 anchors, a positive and a
#: negative), enough for every trainable part to get a gradient.
SMALL_FINETUNING = (*SMALL_VALIDATION, "sampler.anchors=2", "sampler.positives=1", "sampler.negatives=1")


@pytest.fixture
def hub_cache(tmp_path, monkeypatch):
    """torch.hub's cache holding CosPlace's and EigenPlaces' repositories (their published layout)."""
    for folder in ("gmberton_cosplace_main", "gmberton_eigenplaces_main"):
        (tmp_path / "hub" / folder).mkdir(parents=True)
        (tmp_path / "hub" / folder / "hubconf.py").write_text(GEOLOCALIZATION_HUBCONF)
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    return tmp_path / "hub"


def test_every_preset_is_its_authors_recipe_on_its_published_architecture(hub_cache):
    expected = {  # preset: (model, optimizer, lr, training image size, blocks of the ViT kept fixed)
        "salad": ("dinov2_salad", "torch.optim.AdamW", 6e-5, [224, 224], 8),
        "boq": ("dinov2_boq", "torch.optim.AdamW", 1e-4, [224, 224], 10),
        "megaloc": ("dinov2_megaloc", "torch.optim.AdamW", 6e-5, [224, 224], 8),
        "cosplace": ("cosplace", "torch.optim.Adam", 1e-5, [512, 512], None),
        "eigenplaces": ("eigenplaces", "torch.optim.Adam", 1e-5, [512, 512], None),
    }
    for preset, (model, optimizer, lr, size, fixed_blocks) in expected.items():
        cfg = helpers.compose_config("train", f"finetune={preset}", "device=cpu", *PRESETS[preset][1])
        assert (cfg.model.name, cfg.module.optimizer._target_, cfg.module.optimizer.lr) == (model, optimizer, lr)
        assert list(cfg.datamodule.image_size) == size
        network = instantiate(cfg.model).network
        frozen = set(freeze_parameters(network, list(cfg.module.frozen)))
        if fixed_blocks is not None:  # DINOv2's first blocks and embeddings fixed, its last blocks and the head not
            assert {f"backbone.timm.blocks.{i}.attn.qkv.weight" for i in range(fixed_blocks)} <= frozen
            assert not {f"backbone.timm.blocks.{i}.attn.qkv.weight" for i in range(fixed_blocks, 12)} & frozen
            assert "backbone.timm.pos_embed" in frozen and not any(name.startswith("pooling.") for name in frozen)
            assert network.output_dim == {"salad": 8448, "boq": 12288, "megaloc": 8448}[preset]
        else:  # the ResNet's conv1, bn1, layer1 and layer2
            stages = {name.split(".")[2] for name in frozen}
            assert stages == {"0", "1", "4", "5"} and not any("aggregation" in name for name in frozen)


@pytest.mark.slow
@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_each_preset_builds_and_takes_training_steps_with_its_fixed_parts_unchanged(preset, hub_cache, tmp_path):
    hub_folder, overrides = PRESETS[preset]
    vit = hub_folder is None
    cfg = train_config(
        tmp_path,
        f"finetune={preset}",
        *overrides,
        *SMALL_HEADS.get(preset, ()),
        *SMALL_FINETUNING,
        "datamodule.image_size=[126,126]" if vit else "datamodule.image_size=[96,72]",
        "sampler.batches_per_epoch=1",
        "paradigms.approximation.k=[1,3]",
        image_side="model.size=[126,126]" if vit else "model.preprocessing.max_side=96",
    )
    network = instantiate(cfg.model).network  # the weights training starts from (seeded), built once here
    initial = network.state_dict()
    frozen = set(freeze_parameters(network, list(cfg.module.frozen)))  # names only: the values stay as built
    validator = train(cfg, tmp_path / "run")
    assert sorted({entry["epoch"] for entry in validator.history}) == [-1, 0]
    trained = embedded_checkpoint(load_torch_file(tmp_path / "run" / "checkpoints" / "last.ckpt"))["state_dict"]
    trainable = {name for name, _ in network.named_parameters()} - frozen
    assert frozen and trainable
    assert all(torch.equal(trained[name], initial[name]) for name in frozen)
    moved = {name for name in trainable if not torch.equal(trained[name], initial[name])}
    assert len(moved) > len(trainable) // 2  # the step reached the head and the unfrozen blocks


def test_a_learning_rate_per_part_of_any_network_first_pattern_first():
    """Adam's first step moves each parameter by its group's learning rate (m / sqrt(v) = +-1)."""
    torch.manual_seed(0)
    trunk = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3, stride=2), torch.nn.Conv2d(8, 8, 1), torch.nn.Sigmoid())
    network = RetrievalNet(trunk, GeMPooling(8, 3.0, trainable=False), 8, whitening=torch.nn.Linear(8, 4))
    module = helpers.training_module(
        network, lr_scales={"backbone.1.*": 0.1, "backbone.*": 0.5, "whitening.weight": 20.0}
    )
    optimizer = module.configure_optimizers()
    before = {name: p.detach().clone() for name, p in network.named_parameters()}
    network(torch.rand(2, 3, 16, 16)).pow(3).sum().backward()
    optimizer.step()
    expected = {"backbone.0.weight": 5e-4, "backbone.1.weight": 1e-4, "whitening.weight": 2e-2, "whitening.bias": 1e-3}
    for name, step in expected.items():
        moved = (network.get_parameter(name).detach() - before[name]).abs()
        torch.testing.assert_close(moved, torch.full_like(moved, step), atol=step * 1e-2, rtol=0)
    assert [group["name"] for group in optimizer.param_groups] == [
        "backbone.*",
        "backbone.1.*",
        "whitening.weight",
        "network",
    ]
    # with head_lr_scale: the patterns first, then the head's scale outside the backbone
    module = helpers.training_module(network, lr_scales={"whitening.bias": 3.0}, head_lr_scale=10.0)
    rates = {group["name"]: group["lr"] for group in module.configure_optimizers().param_groups}
    assert rates == pytest.approx({"backbone": 1e-3, "whitening.bias": 3e-3, "head": 1e-2})
    with pytest.raises(SettingError, match=r"lr_scales.*'projection.\*' matches no parameter of the network"):
        helpers.training_module(network, lr_scales={"projection.*": 2.0})
    with pytest.raises(ValueError, match="module.lr_scales factors must be positive"):
        helpers.training_module(network, lr_scales={"backbone.*": 0.0})


def test_lr_scales_from_the_command_line(tmp_path):
    cfg = train_config(tmp_path, "module.lr_scales={pooling.*: 10.0, backbone.timm.blocks.*: 0.5}")
    assert dict(cfg.module.lr_scales) == {"pooling.*": 10.0, "backbone.timm.blocks.*": 0.5}


@pytest.mark.parametrize("frozen", [True, False])
def test_frozen_batch_norm_keeps_the_pretrained_statistics_while_the_weights_learn(tmp_path, frozen):
    from locretrieval.models.files.weights import EMBEDDED_CHECKPOINT_KEY

    # SMALL_VALIDATION: the point is the training steps' effect on the batch norms, not validation
    cfg = train_config(tmp_path, f"module.freeze_batch_norm={frozen}", *SMALL_VALIDATION)
    train(cfg, tmp_path / "run")
    trained = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)[EMBEDDED_CHECKPOINT_KEY][
        "state_dict"
    ]
    initial = instantiate(cfg.model).network.state_dict()
    statistics = [key for key in initial if key.endswith(("running_mean", "running_var"))]
    affine = [key.replace("running_mean", "weight") for key in statistics if key.endswith("running_mean")]
    assert len(statistics) > 50
    assert all(torch.equal(trained[key], initial[key]) for key in statistics) == frozen
    assert not all(torch.equal(trained[key], initial[key]) for key in affine)  # batch-norm scales learn either way


@pytest.mark.slow
def test_frozen_parameters_keep_their_pretrained_values(tmp_path):
    from locretrieval.models.files.weights import EMBEDDED_CHECKPOINT_KEY

    patterns = "module.frozen=['backbone.timm.conv_stem.*','backbone.timm.blocks.[0-3].*']"
    cfg = train_config(tmp_path, patterns, *SMALL_VALIDATION)  # the steps matter here, not validation
    train(cfg, tmp_path / "run")
    trained = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)[EMBEDDED_CHECKPOINT_KEY][
        "state_dict"
    ]
    network = instantiate(cfg.model).network
    initial = dict(network.named_parameters())
    frozen = [
        name for name in initial if re.fullmatch(r"backbone\.timm\.(conv_stem|blocks\.[0-3])\..*", name)
    ]  # stages 0-3
    assert len(frozen) > 20
    assert all(torch.equal(trained[name], initial[name]) for name in frozen)
    assert not any(
        torch.equal(trained[name], initial[name])
        for name in ("backbone.timm.conv_head.weight", "backbone.timm.blocks.6.0.conv_pwl.weight")
    )
    with pytest.raises(ConfigError, match=r"module.frozen: 'backbone.trunk.\*' matches no parameter"):
        train(
            train_config(tmp_path / "bad", "module.frozen=['backbone.trunk.*']", *SMALL_VALIDATION),
            tmp_path / "bad" / "run",
        )


def test_a_diverging_run_stops_at_the_step_naming_the_loss_and_the_learning_rate(tmp_path):
    from locretrieval.training.module import TrainingDiverged

    cfg = train_config(
        tmp_path,
        "module.optimizer.lr=1e6",
        "trainer.max_epochs=3",
        "sampler.batches_per_epoch=3",
        *SMALL_VALIDATION,  # the divergence is in the training steps: a cheap validation before them
    )
    with pytest.raises(
        TrainingDiverged,
        match=r"training diverged at step \d+ \(epoch \d\): (the loss is nan|the loss is inf|the gradient "
        r"of .* is not finite), learning rate \[.*\] \(module.optimizer.lr\); lower module.optimizer.lr",
    ):
        train(cfg, tmp_path / "run")
    for checkpoint in (tmp_path / "run" / "checkpoints").glob(
        "*.ckpt"
    ):  # what was saved before holds finite weights only
        state = torch.load(checkpoint, weights_only=False)["state_dict"]
        assert all(torch.isfinite(value).all() for value in state.values() if value.is_floating_point())


@pytest.mark.parametrize("frozen_backbone", [False, True])
def test_head_lr_scale_moves_the_head_that_much_faster_than_the_backbone(frozen_backbone):
    """Adam's first step moves every parameter by its group's learning rate (m / sqrt(v) = +-1)."""
    from functools import partial

    from locretrieval.models.networks import GeMPooling, RetrievalNet

    torch.manual_seed(0)
    trunk = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3, stride=2), torch.nn.ReLU())
    network = RetrievalNet(trunk, GeMPooling(8, 3.0, trainable=False), 8, whitening=torch.nn.Linear(8, 4))
    module = helpers.training_module(
        network,
        scheduler=partial(torch.optim.lr_scheduler.CosineAnnealingLR, T_max=4),
        frozen=["backbone.*"] if frozen_backbone else [],
        head_lr_scale=10.0,
    )
    optimizers = module.configure_optimizers()
    optimizer = optimizers["optimizer"]
    before = {name: p.detach().clone() for name, p in network.named_parameters()}
    network(torch.rand(2, 3, 16, 16)).pow(3).sum().backward()
    optimizer.step()
    steps = {name: (p.detach() - before[name]).abs() for name, p in network.named_parameters()}
    torch.testing.assert_close(steps["whitening.weight"], torch.full((4, 8), 1e-2), atol=1e-5, rtol=0)
    trunk_step = 0.0 if frozen_backbone else 1e-3
    torch.testing.assert_close(steps["backbone.0.weight"], torch.full((8, 3, 3, 3), trunk_step), atol=1e-6, rtol=0)
    assert [group["name"] for group in optimizer.param_groups] == (
        ["head"] if frozen_backbone else ["backbone", "head"]
    )
    optimizers["lr_scheduler"].step()  # the schedule keeps the ratio
    rates = {group["name"]: group["lr"] for group in optimizer.param_groups}
    assert rates["head"] == pytest.approx(1e-2 * (1 + np.cos(np.pi / 4)) / 2)
    if not frozen_backbone:
        assert rates["head"] == pytest.approx(10 * rates["backbone"])
    plain = helpers.training_module(network).configure_optimizers()
    assert len(plain.param_groups) == 1 and plain.param_groups[0]["lr"] == 1e-3  # scale 1: one group, as before 0.9.0
    with pytest.raises(ValueError, match="module.head_lr_scale must be positive"):
        helpers.training_module(network, head_lr_scale=0)
    with pytest.raises(
        ValueError, match="module.head_lr_scale=10.0 needs a network with a backbone .* Sequential has no 'backbone'"
    ):
        helpers.training_module(trunk, head_lr_scale=10.0)


class TemperatureLoss(torch.nn.Module):
    """A loss with a parameter: ListNet-style cross-entropy at a learned temperature."""

    def __init__(self, temperature: float = 0.1) -> None:
        super().__init__()
        self.log_temperature = torch.nn.Parameter(torch.tensor(float(np.log(temperature))))

    def forward(self, descriptors, relevance, negatives):
        scores = descriptors @ descriptors.T / self.log_temperature.exp()
        target = relevance / relevance.sum(1, keepdim=True).clamp_min(1e-9)
        mask = (relevance > 0) | negatives
        logits = scores.masked_fill(~mask, -1e4)
        rows = relevance.sum(1) > 0
        return -(target * torch.log_softmax(logits, 1))[rows].sum(1).mean()


@pytest.mark.parametrize("head_lr_scale", [1.0, 10.0])
def test_the_parameters_of_a_loss_are_optimized(tmp_path, head_lr_scale):
    from functools import partial

    from locretrieval.models.networks import GeMPooling, RetrievalNet

    torch.manual_seed(0)
    network = RetrievalNet(
        torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3, stride=2), torch.nn.ReLU()), GeMPooling(8, 3.0, trainable=False), 8
    )
    loss = TemperatureLoss()
    module = helpers.training_module(network, loss, partial(torch.optim.Adam, lr=1e-2), head_lr_scale=head_lr_scale)
    optimizer = module.configure_optimizers()
    assert any(parameter is loss.log_temperature for group in optimizer.param_groups for parameter in group["params"])
    before = loss.log_temperature.item()
    relevance = torch.tensor([[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1], [0, 0, 1, 0]], dtype=torch.float32)
    module.batch_loss(
        (torch.randint(0, 255, (4, 3, 16, 16), dtype=torch.uint8), relevance, relevance == 0, torch.arange(4))
    ).backward()
    optimizer.step()
    assert loss.log_temperature.item() != before  # the loss learned (Adam: by the learning rate)
    assert abs(abs(loss.log_temperature.item() - before) - 1e-2) < 1e-4
