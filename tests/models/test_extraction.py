"""The extraction engine and the trainable heads: sizes, scales, determinism, caching, weights, each
layer's own mode restored."""

import hashlib
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import torchvision
from helpers import evaluate_config
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from PIL import Image

from locretrieval.cache import tree_signature
from locretrieval.config import ConfigError
from locretrieval.models import TrainableDescriptor
from locretrieval.models.extraction import IMAGENET_MEAN, IMAGENET_STD
from locretrieval.models.files.weights import HASH_CACHE_ENV, MissingWeightsError, content_sha256
from locretrieval.models.networks import l2_normalize
from locretrieval.models.torch_descriptor import RANDOM_INIT_SUFFIX
from locretrieval.models.trainable.backbones import TorchvisionBackbone
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.scene import Camera, ImageSet, Scene

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "model"
#: (width, height) of the test images: three sizes, interleaved.
SIZES = [(64, 48), (48, 64), (64, 48), (80, 60), (48, 64)]


@pytest.fixture(autouse=True)
def hash_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(HASH_CACHE_ENV, str(tmp_path / "hashes"))


def camera(width: int, height: int) -> Camera:
    return Camera("PINHOLE", width, height, (50.0, 50.0, width / 2, height / 2))


def write_images(folder: Path, sizes, seed: int = 0, prefix: str = "img") -> ImageSet:
    rng = np.random.default_rng(seed)
    names = []
    for i, (width, height) in enumerate(sizes):
        names.append(f"{prefix}{i}.png")
        Image.fromarray(rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)).save(folder / names[-1])
    n = len(names)
    return ImageSet(
        names, folder, [camera(*size) for size in sizes], [[1.0, 0, 0, 0]] * n, [[0.0, 0, float(i)] for i in range(n)]
    )


NETVLAD = {"_target_": "locretrieval.models.networks.NetVLADPooling", "clusters": 8}
GEM = {"_target_": "locretrieval.models.networks.GeMPooling", "p": 3.0, "trainable": True}
EXTRACTION = {
    "device": "cpu",
    "batch_size": 4,
    "num_workers": 0,
    "mixed_precision": False,
    "progress": False,
    "memmap_dir": None,
}


def trainable(extraction=(), **options) -> TrainableDescriptor:
    """A ResNet-18 model as configs/model/gem.yaml builds it, with ``options`` and ``extraction`` overrides."""
    settings = dict(
        name="gem",
        backbone=TorchvisionBackbone("resnet18"),
        pooling=GEM,
        whiten_dim=None,
        weights=None,
        random_init=False,
        seed=0,
        max_side=None,
        scales=[1.0],
    )
    return TrainableDescriptor(**{**settings, **options}, extraction={**EXTRACTION, **dict(extraction)})


def gem(batch_size=4, num_workers=0, memmap_dir=None, device="cpu", **options) -> TrainableDescriptor:
    """A randomly initialised GeM model."""
    extraction = {"batch_size": batch_size, "num_workers": num_workers, "memmap_dir": memmap_dir, "device": device}
    return trainable(extraction, **{"random_init": True, **options})


@pytest.fixture
def images(tmp_path):
    return write_images(tmp_path, SIZES)


def reference(model, images: ImageSet, scales=(1.0,)) -> np.ndarray:
    """Each image alone: normalise, run each scale, sum unit descriptors, L2."""
    rows = []
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    with torch.no_grad():
        for path in images.paths:
            x = torch.from_numpy(np.array(Image.open(path).convert("RGB"))).permute(2, 0, 1)[None].float()
            x = (x / 255 - mean) / std
            total = 0
            for scale in scales:
                size = (round(x.shape[2] * scale), round(x.shape[3] * scale))
                scaled = x if scale == 1 else F.interpolate(x, size=size, mode="bilinear", align_corners=False)
                total = total + model.network.eval()(scaled)
            rows.append(l2_normalize(total)[0].numpy())
    return np.stack(rows)


def test_batches_of_mixed_sizes_equal_one_image_at_a_time(images):
    model = gem(batch_size=2)
    descriptors = model.describe(images)
    assert descriptors.dtype == np.float32 and descriptors.shape == (5, 512)
    np.testing.assert_allclose(descriptors, reference(model, images), atol=1e-5)
    stats = model.last_stats
    assert stats.images == 5 and stats.forward_calls == 3  # (64x48: 2), (48x64: 2), (80x60: 1)
    assert stats.sizes == set(SIZES)


def test_camera_sizes_that_disagree_with_the_files_still_work(images):
    wrong = ImageSet(images.names, images.image_root, [camera(64, 48)] * 5, images.qvec, images.tvec)
    model = gem(batch_size=8)
    np.testing.assert_allclose(model.describe(wrong), reference(model, images), atol=1e-5)
    assert model.last_stats.forward_calls == 3


def test_extraction_is_deterministic_and_seeded(images):
    first, second = gem(batch_size=2), gem(batch_size=2)
    np.testing.assert_array_equal(first.describe(images), second.describe(images))
    np.testing.assert_array_equal(first.describe(images), first.describe(images))
    assert not np.allclose(first.describe(images), gem(seed=1).describe(images), atol=1e-3)


def test_workers_and_memory_maps_give_the_same_descriptors(images, tmp_path):
    in_memory = gem(batch_size=2).describe(images)
    mapped = gem(batch_size=2, num_workers=2, memmap_dir=str(tmp_path / "maps")).describe(images)
    assert isinstance(mapped, np.memmap) and len(list((tmp_path / "maps").glob("*.npy"))) == 1
    np.testing.assert_array_equal(np.asarray(mapped), in_memory)


def test_max_side_shrinks_before_the_network(tmp_path):
    images = write_images(tmp_path, [(100, 80), (40, 30)])
    model = gem(max_side=50)
    model.describe(images)
    assert model.last_stats.sizes == {(50, 40), (40, 30)}


def test_multi_scale_sums_unit_descriptors_of_each_scale(images):
    model = gem(scales=[0.5, 1.0, 1.5])
    np.testing.assert_allclose(model.describe(images), reference(model, images, (0.5, 1.0, 1.5)), atol=1e-5)
    assert not np.allclose(model.describe(images), reference(model, images), atol=1e-3)


def test_second_run_reads_the_cache_without_a_forward_pass(tmp_path):
    (tmp_path / "db").mkdir()
    (tmp_path / "q").mkdir()
    database = write_images(tmp_path / "db", SIZES[:3], seed=0)
    queries = write_images(tmp_path / "q", SIZES[3:], seed=1)
    scene = Scene("toy", database, queries)
    calls = []
    first = gem()
    first.network.register_forward_hook(lambda *args: calls.append(1))
    db, q = describe_scene(first, scene, tmp_path / "cache")
    assert len(calls) == 4 and db.shape == (3, 512) and q.shape == (2, 512)  # two sizes in each set

    calls.clear()
    second = gem()
    second.network.register_forward_hook(lambda *args: calls.append(1))
    db_again, q_again = describe_scene(second, scene, tmp_path / "cache")
    assert calls == []
    np.testing.assert_array_equal(db_again, db)
    np.testing.assert_array_equal(q_again, q)
    assert gem(seed=1).identity() != first.identity()


def test_random_initialisation_is_explicit_and_stated(tmp_path):
    with pytest.raises(MissingWeightsError, match=r"resnet18-f37072fd\.pth.*download\.pytorch\.org.*random_init=true"):
        trainable()
    model = gem()
    assert model.name == f"gem{RANDOM_INIT_SUFFIX}"
    weights = model.identity()["weights"]
    assert (
        weights["sha256"] is None and weights["seed"] == 0 and "backbone.conv1.weight" in weights["random_parameters"]
    )
    assert "pooling.p" not in weights["random_parameters"]  # set by the configuration


def test_torchvision_checkpoint_fills_the_backbone_only(images, tmp_path):
    torch.manual_seed(5)
    resnet = torchvision.models.resnet18(weights=None)
    path = tmp_path / "resnet18-f37072fd.pth"
    torch.save(resnet.state_dict(), path)

    model = trainable(weights=path)
    assert model.name == "gem" and model.identity()["weights"]["random_parameters"] == []
    trunk = torch.nn.Sequential(*list(resnet.children())[:-2]).eval()
    for name, tensor in trunk.state_dict().items():
        prefix, rest = name.split(".", 1)
        key = ["conv1", "bn1", "relu", "maxpool", "layer1", "layer2", "layer3", "layer4"][int(prefix)] + "." + rest
        torch.testing.assert_close(model.network.state_dict()[f"backbone.{key}"], tensor, rtol=0, atol=0)

    with pytest.raises(ValueError, match="pooling.*random_init=true"):
        trainable(name="netvlad_head", pooling=NETVLAD, weights=path)
    vlad = trainable(name="netvlad_head", pooling=NETVLAD, weights=path, random_init=True)
    assert sorted(vlad.identity()["weights"]["random_parameters"]) == ["pooling.assignment.weight", "pooling.centers"]
    assert vlad.describe(images).shape == (5, 512 * 8)


def test_saved_checkpoints_load_back_and_must_match_the_architecture(images, tmp_path):
    model = gem(whiten_dim=32)
    path = tmp_path / "trained.pt"
    model.save_checkpoint(path)
    loaded = trainable(whiten_dim=32, weights=path)
    assert loaded.name == "gem" and not loaded.weights.random_init
    np.testing.assert_array_equal(loaded.describe(images), model.describe(images))
    with pytest.raises(ValueError, match="whiten_dim: file 32 vs config 64"):
        trainable(whiten_dim=64, weights=path)


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present")
def test_cuda_without_a_gpu_is_an_error():
    with pytest.raises(RuntimeError, match="no CUDA GPU"):
        gem(device="cuda")


def test_extraction_settings_are_checked_and_misspelt_ones_are_errors():
    assert gem(batch_size=3).settings.batch_size == 3
    with pytest.raises(
        ConfigError, match=r"model.extraction.batchsize: unknown key; expected one of \['device', 'batch_size'"
    ):
        trainable({"batchsize": 3}, random_init=True)
    with pytest.raises(ConfigError, match=r"model.extraction.batch_size: must be >= 1, got 0"):
        gem(batch_size=0)


@pytest.mark.parametrize(
    "model, expected",
    [
        ("netvlad", r"Pitts30K_struct\.mat"),
        ("apgem", r"Resnet101-AP-GeM-LM18\.pt"),
        ("delg", r"r101delg_gldv2clean_20200914"),
        ("gem", r"resnet50-11ad3fa6\.pth"),
        ("netvlad_head", r"vgg16-397923af\.pth"),
    ],
)
def test_model_configs_name_the_missing_weights(model, expected, tmp_path):
    config = evaluate_config(f"model={model}", "device=cpu", f"paths.data_dir={tmp_path}")
    with pytest.raises(InstantiationException) as error:
        instantiate(config.model)
    assert isinstance(error.value.__cause__, MissingWeightsError)
    assert re.search(expected, str(error.value.__cause__))


def test_gem_config_instantiates_with_random_weights_when_asked(images):
    config = evaluate_config(
        "model=gem",
        "device=cpu",
        "model.backbone.name=resnet18",
        "model.random_init=true",
        "model.scales=[0.5,1.0]",
        "model.extraction.num_workers=0",
        "model.extraction.progress=false",
    )
    model = instantiate(config.model)
    assert isinstance(model, TrainableDescriptor) and model.name == f"gem{RANDOM_INIT_SUFFIX}"
    assert model.preprocessing.scales == (0.5, 1.0) and model.describe(images).shape == (5, 512)


def test_weight_hashes_are_cached_by_path_size_and_mtime(tmp_path):
    path = tmp_path / "weights.pt"
    path.write_bytes(b"first version")
    assert content_sha256(path) == hashlib.sha256(b"first version").hexdigest()
    cache_file = tmp_path / "hashes" / "weight_hashes.json"
    cache = json.loads(cache_file.read_text())
    cache[str(path.resolve())]["sha256"] = "from-the-cache"
    cache_file.write_text(json.dumps(cache))
    assert content_sha256(path) == "from-the-cache"  # unchanged file: not re-hashed
    path.write_bytes(b"second version, longer")
    os.utime(path, ns=(1, 1))
    assert content_sha256(path) == hashlib.sha256(b"second version, longer").hexdigest()


def test_weight_folder_hash_covers_relative_names_and_contents(tmp_path):
    folder = tmp_path / "saved_model"
    (folder / "variables").mkdir(parents=True)
    (folder / "saved_model.pb").write_bytes(b"graph")
    (folder / "variables" / "data").write_bytes(b"weights")
    expected = hashlib.sha256(b"saved_model.pb\ngraph" + os.path.join("variables", "data").encode() + b"\nweights")
    assert content_sha256(folder) == expected.hexdigest()
    signature = json.loads((tmp_path / "hashes" / "weight_hashes.json").read_text())[str(folder.resolve())]["signature"]
    assert [entry[:2] for entry in signature] == [["saved_model.pb", 5], [os.path.join("variables", "data"), 7]]
    assert tree_signature(folder / "saved_model.pb") == [("", 5, (folder / "saved_model.pb").stat().st_mtime_ns)]
    assert tree_signature(tmp_path / "absent") == []


def test_evaluation_mode_restores_each_layers_own_mode():
    from locretrieval.models.extraction import evaluation_mode

    network = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3), torch.nn.BatchNorm2d(4), torch.nn.Dropout()).train()
    network[1].eval()  # frozen batch norm in a training network
    with evaluation_mode(network):
        assert not any(layer.training for layer in network.modules())
    assert [layer.training for layer in network.modules()] == [True, True, False, True]
