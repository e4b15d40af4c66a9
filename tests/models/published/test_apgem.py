"""AP-GeM: dirtorch checkpoints with pickled scikit-learn PCA objects, without scikit-learn."""

import os
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch
import torchvision
from helpers import ObjectPointerArray, error_in_subprocess, run_python, zoo_model
from PIL import Image

from locretrieval.models.files.weights import HASH_CACHE_ENV, MissingWeightsError, save_checkpoint
from locretrieval.models.published.apgem import convert_apgem
from locretrieval.scene import Camera, ImageSet

MEAN, STD = [0.40, 0.50, 0.60], [0.20, 0.25, 0.30]
OUT_DIM, GEM_P = 32, 3.3


@pytest.fixture(autouse=True)
def hash_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(HASH_CACHE_ENV, str(tmp_path / "hashes"))


class FakeSklearnPCA:
    """Pickles as ``sklearn.decomposition.pca.PCA``, as in checkpoints saved with scikit-learn 0.20."""


FakeSklearnPCA.__module__, FakeSklearnPCA.__qualname__, FakeSklearnPCA.__name__ = (
    "sklearn.decomposition.pca",
    "PCA",
    "PCA",
)


@pytest.fixture
def sklearn_modules(monkeypatch):
    """Make the old module path importable while pickling (scikit-learn is not installed here)."""
    for name in ("sklearn", "sklearn.decomposition", "sklearn.decomposition.pca"):
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
    sys.modules["sklearn.decomposition.pca"].PCA = FakeSklearnPCA


def fabricated_pca(rng: np.random.Generator, dim: int) -> FakeSklearnPCA:
    pca = FakeSklearnPCA()
    components = np.linalg.qr(rng.normal(size=(dim, dim)))[0]
    variance = np.sort(rng.uniform(0.01, 1.0, size=dim))[::-1]
    pca.__dict__.update(
        n_components=None,
        copy=True,
        whiten=True,
        svd_solver="full",
        tol=0.0,
        iterated_power="auto",
        random_state=None,
        mean_=rng.normal(size=dim) * 0.05,
        n_samples_=np.int64(1000),
        n_features_=dim,
        n_components_=dim,
        components_=components,
        explained_variance_=variance,
        explained_variance_ratio_=variance / variance.sum(),
        singular_values_=np.sqrt(variance * 999),
        noise_variance_=np.float64(0.0),
        _sklearn_version="0.20.2",
    )
    return pca


def dirtorch_state_dict(arch: str, seed: int) -> dict[str, torch.Tensor]:
    torch.manual_seed(seed)
    resnet = torchvision.models.get_model(arch, weights=None)
    for module in resnet.modules():
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.1, 0.1)
            module.running_var.uniform_(0.5, 1.5)
    state = {k: v for k, v in resnet.state_dict().items() if not k.startswith("fc.")}
    state["adpool.p"] = torch.tensor([GEM_P])
    fc = torch.nn.Linear(resnet.fc.in_features, OUT_DIM)
    state["fc.weight"], state["fc.bias"] = fc.weight.detach(), fc.bias.detach()
    return state


@pytest.fixture
def checkpoint(tmp_path, sklearn_modules):
    """A dirtorch checkpoint as saved from DataParallel (``module.`` names) with a pickled PCA."""
    state = dirtorch_state_dict("resnet18", seed=0)
    pca = fabricated_pca(np.random.default_rng(0), OUT_DIM)
    path = tmp_path / "Resnet18-AP-GeM-test.pt"
    torch.save(
        {
            "state_dict": {f"module.{k}": v for k, v in state.items()},
            "model_options": {
                "arch": "resnet18_rmac",
                "out_dim": OUT_DIM,
                "pooling": "gem",
                "gemp": 3,
                "dropout_p": None,
            },
            "preprocess": {"mean": MEAN, "std": STD, "input_size": 224},
            "pca": {"Landmarks_clean": pca},
            "epoch": 7,
        },
        path,
    )
    return path, state, pca


def reference_apgem(rgb: np.ndarray, state: dict, pca=None, power=0.5, dims=None) -> np.ndarray:
    """dirtorch's computation: ResNet -> GeM -> FC -> L2 (-> PCA transform -> L2), in float64."""
    resnet = torchvision.models.resnet18(weights=None).double().eval()
    resnet.load_state_dict({k: v for k, v in state.items() if not k.startswith(("fc.", "adpool."))}, strict=False)
    x = (rgb / 255.0 - np.array(MEAN)) / np.array(STD)
    with torch.no_grad():
        f = torch.from_numpy(x.transpose(2, 0, 1)[None].copy())
        for name in ("conv1", "bn1", "relu", "maxpool", "layer1", "layer2", "layer3", "layer4"):
            f = getattr(resnet, name)(f)
    f = f[0].numpy()
    pooled = (np.clip(f, 1e-6, None) ** GEM_P).mean(axis=(1, 2)) ** (1 / GEM_P)
    d = state["fc.weight"].double().numpy() @ pooled + state["fc.bias"].double().numpy()
    d /= np.linalg.norm(d)
    if pca is not None:
        d = (d - pca.mean_) @ pca.components_[:dims].T / pca.explained_variance_[:dims] ** power
        d /= np.linalg.norm(d)
    return d


def image_set(folder: Path, images: list[np.ndarray]) -> ImageSet:
    names, cameras = [], []
    for i, rgb in enumerate(images):
        names.append(f"img{i}.png")
        Image.fromarray(rgb).save(folder / names[-1])
        cameras.append(Camera("PINHOLE", rgb.shape[1], rgb.shape[0], (50.0, 50.0, rgb.shape[1] / 2, rgb.shape[0] / 2)))
    return ImageSet(names, folder, cameras, [[1.0, 0, 0, 0]] * len(names), [[0.0, 0, 0]] * len(names))


@pytest.fixture
def images(tmp_path):
    rng = np.random.default_rng(3)
    rgbs = [
        rng.integers(0, 256, size=(40, 56, 3), dtype=np.uint8),
        rng.integers(0, 256, size=(56, 40, 3), dtype=np.uint8),
    ]
    return rgbs, image_set(tmp_path, rgbs)


def test_dirtorch_checkpoint_matches_dirtorch_computation(checkpoint, images):
    path, state, pca = checkpoint
    rgbs, image_set_ = images
    model = zoo_model("apgem", weights=path, backbone="resnet18", out_dim=OUT_DIM)
    plain = model.describe(image_set_)
    for row, rgb in zip(plain, rgbs):
        np.testing.assert_allclose(row, reference_apgem(rgb, state), atol=1e-5)
    assert model.preprocessing.mean == tuple(MEAN) and model.identity()["architecture"]["pca"] is None

    whitened_model = zoo_model(
        "apgem",
        weights=path,
        backbone="resnet18",
        out_dim=OUT_DIM,
        pca="Landmarks_clean",
        pca_power=0.25,
        pca_dims=16,
    )
    whitened = whitened_model.describe(image_set_)
    assert whitened.shape == (2, 16)
    for row, rgb in zip(whitened, rgbs):
        np.testing.assert_allclose(row, reference_apgem(rgb, state, pca, power=0.25, dims=16), atol=1e-5)
    assert whitened_model.identity() != model.identity()


def test_converted_checkpoint_needs_no_sklearn_and_gives_the_same_descriptors(checkpoint, images, tmp_path):
    path, _, _ = checkpoint
    converted = tmp_path / "apgem.pt"
    convert_apgem(path, converted)
    for name in ("sklearn", "sklearn.decomposition", "sklearn.decomposition.pca"):
        sys.modules.pop(name)
    content = torch.load(converted, weights_only=True)  # plain tensors and containers only
    assert set(content["extra"]["pca"]) == {"Landmarks_clean"}
    options = dict(backbone="resnet18", out_dim=OUT_DIM, pca="Landmarks_clean")
    original = zoo_model("apgem", weights=path, **options).describe(images[1])
    again = zoo_model("apgem", weights=converted, **options).describe(images[1])
    np.testing.assert_array_equal(again, original)


def test_file_must_hold_the_configured_architecture(checkpoint, tmp_path):
    path, _, _ = checkpoint
    converted = tmp_path / "apgem.pt"
    convert_apgem(path, converted)
    for weights in (path, converted):
        with pytest.raises(
            ValueError, match=r"differs from the configuration \(backbone: file 'resnet18' vs config 'resnet50'\)"
        ):
            zoo_model("apgem", weights=weights, backbone="resnet50", out_dim=OUT_DIM)
        with pytest.raises(ValueError, match=rf"out_dim: file {OUT_DIM} vs config 64"):
            zoo_model("apgem", weights=weights, backbone="resnet18", out_dim=64)
    netvlad = tmp_path / "netvlad.pt"
    save_checkpoint(netvlad, "netvlad", {"clusters": 4}, {}, {})
    with pytest.raises(ValueError, match="netvlad.pt: a locretrieval checkpoint of model 'netvlad', not 'apgem'"):
        zoo_model("apgem", weights=netvlad, backbone="resnet18", out_dim=OUT_DIM)


class Payload:
    def __reduce__(self):
        return (os.system, ("echo should-not-run",))


def test_unexpected_pickled_objects_are_refused(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"state_dict": {}, "model_options": {"arch": "resnet18_rmac"}, "payload": Payload()}, path)
    with pytest.raises(ValueError, match="evil.pt: refused to unpickle"):
        zoo_model("apgem", weights=path, backbone="resnet18")


def test_resnet101_checkpoint_layout_loads(tmp_path):
    with torch.device("meta"):
        shapes = torchvision.models.resnet101(weights=None).state_dict()
    state = {f"module.{k}": torch.zeros(v.shape, dtype=v.dtype) for k, v in shapes.items() if not k.startswith("fc.")}
    state.update(
        {
            "module.adpool.p": torch.tensor([3.0]),
            "module.fc.weight": torch.zeros(2048, 2048),
            "module.fc.bias": torch.zeros(2048),
        }
    )
    path = tmp_path / "Resnet101-AP-GeM-LM18.pt"
    torch.save(
        {"state_dict": state, "model_options": {"arch": "resnet101_rmac", "out_dim": 2048, "pooling": "gem"}}, path
    )
    model = zoo_model("apgem", weights=path)
    assert model.network.output_dim == 2048
    assert sum(p.numel() for p in model.network.parameters()) == sum(
        v.numel() for k, v in state.items() if "num_batches" not in k and "running" not in k
    )


def test_missing_file_names_the_expected_file_and_its_publisher(tmp_path):
    with pytest.raises(MissingWeightsError, match=r"Resnet101-AP-GeM-LM18\.pt.*deep-image-retrieval"):
        zoo_model("apgem", weights=tmp_path / "absent.pt")


def test_a_crafted_numpy_dtype_in_a_dirtorch_file_is_refused_not_a_crash(tmp_path, sklearn_modules):
    pca = fabricated_pca(np.random.default_rng(0), 4)
    pca.mean_ = ObjectPointerArray()  # read through torch's restricted unpickler, numpy allowlisted
    path = tmp_path / "Resnet18-AP-GeM-crafted.pt"
    state = {"fc.weight": torch.zeros(4, 512), "fc.bias": torch.zeros(4), "adpool.p": torch.ones(1)}
    torch.save({"state_dict": state, "model_options": {"arch": "resnet18_rmac"}, "pca": {"x": pca}}, path)
    process = error_in_subprocess("locretrieval.models.published.apgem.read_apgem_weights", path)
    assert process.returncode == 0, process.stderr[-2000:]  # -11 (SIGSEGV) before the stand-ins
    assert process.stdout.startswith(f"{path}: refused to unpickle an object this loader does not allow")
    assert "refused dtype 'V8' with fields or a sub-array" in process.stdout
    script = run_python(  # the converter users run: a clean error naming the file, no crash
        "import sys\n"
        f"sys.argv = ['convert_weights.py', 'apgem', {str(path)!r}, {str(tmp_path / 'out.pt')!r}]\n"
        "import runpy\n"
        "runpy.run_path('scripts/convert_weights.py', run_name='__main__')\n"
    )
    assert script.returncode == 1 and f"DataFileError: {path}: refused" in script.stderr
    assert not (tmp_path / "out.pt").exists()


def test_numpy_values_of_a_dirtorch_pca_arrive_as_plain_arrays(checkpoint):
    from locretrieval.models.published.apgem import read_apgem_weights

    path, _, pca = checkpoint
    loaded = read_apgem_weights(path).pcas["Landmarks_clean"]
    assert type(loaded.components) is np.ndarray and loaded.components.dtype == np.float64
    np.testing.assert_array_equal(loaded.components, pca.components_)
    np.testing.assert_array_equal(loaded.explained_variance, pca.explained_variance_)
