"""train.py finetune=<preset>: the field's descriptors fine-tuned with their authors' recipes (their
own preprocessing, the parts they keep fixed, their optimizer), each taking training steps; and
a learning rate per part of any network (module.lr_scales)."""

import helpers
import pytest
import torch
from helpers import train
from hydra.utils import instantiate
from training_runs import train_config

from locretrieval.config import SettingError
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
        "datamodule.image_size=[126,126]" if vit else "datamodule.image_size=[96,72]",
        "sampler.batches_per_epoch=1",
        "paradigms.approximation.k=[1,3]",
        image_side="model.size=[126,126]" if vit else "model.preprocessing.max_side=96",
    )
    initial = instantiate(cfg.model).network.state_dict()
    validator = train(cfg, tmp_path / "run")
    assert sorted({entry["epoch"] for entry in validator.history}) == [-1, 0]
    trained = embedded_checkpoint(load_torch_file(tmp_path / "run" / "checkpoints" / "last.ckpt"))["state_dict"]
    network = instantiate(cfg.model).network
    frozen = set(freeze_parameters(network, list(cfg.module.frozen)))
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
