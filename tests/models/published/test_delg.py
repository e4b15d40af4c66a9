"""DELG: TF-Slim variable names -> our state dict, against a forward pass written from TF semantics."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from helpers import zoo_model
from PIL import Image

from locretrieval.models.files.weights import HASH_CACHE_ENV, MissingWeightsError
from locretrieval.models.published.delg import convert_delg, delg_state_dict_from_tf, read_tf_variables
from locretrieval.scene import Camera, ImageSet

SCALES = (0.70710677, 1.0, 1.4142135)
RESNET_101, DEPTHS, STRIDES = (3, 4, 23, 3), (64, 128, 256, 512), (2, 2, 2, 1)
#: A shallower slim ResNet for the forward-pass comparison (same names and layout, fewer units).
SHALLOW = (2, 2, 3, 2)
WHITEN_DIM = 64


@pytest.fixture(autouse=True)
def hash_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(HASH_CACHE_ENV, str(tmp_path / "hashes"))


def slim_variables(rng: np.random.Generator, units: tuple[int, ...], prefix: str = "DELG/") -> dict[str, np.ndarray]:
    """DELG's variables named as tf_slim's resnet_v1_101 names them, plus local-branch extras."""
    variables: dict[str, np.ndarray] = {}

    def conv(name: str, k: int, cin: int, cout: int, gamma: float = 1.0) -> None:
        variables[f"{prefix}{name}/weights:0"] = (
            rng.normal(size=(k, k, cin, cout)) * np.sqrt(2 / (k * k * cin))
        ).astype(np.float32)
        variables[f"{prefix}{name}/BatchNorm/gamma:0"] = (gamma * rng.uniform(0.5, 1.0, cout)).astype(np.float32)
        variables[f"{prefix}{name}/BatchNorm/beta:0"] = rng.normal(0, 0.1, cout).astype(np.float32)
        variables[f"{prefix}{name}/BatchNorm/moving_mean:0"] = rng.normal(0, 0.1, cout).astype(np.float32)
        variables[f"{prefix}{name}/BatchNorm/moving_variance:0"] = rng.uniform(0.5, 1.5, cout).astype(np.float32)

    conv("resnet_v1_101/conv1", 7, 3, 64)
    channels = 64
    for block, (count, depth) in enumerate(zip(units, DEPTHS), start=1):
        for unit in range(1, count + 1):
            scope = f"resnet_v1_101/block{block}/unit_{unit}/bottleneck_v1"
            if unit == 1:
                conv(f"{scope}/shortcut", 1, channels, depth * 4)
            conv(f"{scope}/conv1", 1, channels, depth)
            conv(f"{scope}/conv2", 3, depth, depth)
            conv(f"{scope}/conv3", 1, depth, depth * 4, gamma=0.2)
            channels = depth * 4
    variables[f"{prefix}whitening/weights:0"] = (rng.normal(size=(2048, WHITEN_DIM)) / 45).astype(np.float32)
    variables[f"{prefix}whitening/biases:0"] = rng.normal(0, 0.01, WHITEN_DIM).astype(np.float32)
    variables[f"{prefix}attention/conv1/weights:0"] = rng.normal(size=(1, 1, 1024, 512)).astype(np.float32)
    variables[f"{prefix}attention/conv1/biases:0"] = np.zeros(512, np.float32)
    variables[f"{prefix}autoencoder/weights:0"] = rng.normal(size=(1, 1, 1024, 128)).astype(np.float32)
    variables["global_step:0"] = np.array(500000)
    return variables


def tf_padding(size: int, kernel: int, stride: int) -> tuple[int, int]:
    total = max((-(-size // stride) - 1) * stride + kernel - size, 0)
    return total // 2, total - total // 2


def tf_conv(x: torch.Tensor, kernel: np.ndarray, stride: int) -> torch.Tensor:
    """slim's conv: ``conv2d_same`` (explicit symmetric padding) when strided, else SAME padding.
    Computed as patches x ``[H, W, IN, OUT]`` kernel, without transposing it to PyTorch's layout."""
    k = kernel.shape[0]
    if stride > 1:
        pads = ((k - 1) // 2, k - 1 - (k - 1) // 2) * 2
    else:
        pads = (*tf_padding(x.shape[3], k, 1), *tf_padding(x.shape[2], k, 1))
    x = F.pad(x, pads)
    height, width = (x.shape[2] - k) // stride + 1, (x.shape[3] - k) // stride + 1
    patches = F.unfold(x, k, stride=stride)  # [N, C*k*k, L], channel-major
    matrix = torch.from_numpy(kernel.transpose(2, 0, 1, 3).reshape(-1, kernel.shape[3])).double()
    return torch.einsum("ncl,co->nol", patches, matrix).reshape(x.shape[0], -1, height, width)


def reference_delg(
    rgb: np.ndarray, variables: dict[str, np.ndarray], units: tuple[int, ...], prefix: str = "DELG/"
) -> np.ndarray:
    """DELG's global branch written from TensorFlow's semantics (float64)."""
    v = {name.removesuffix(":0").removeprefix(prefix): value.astype(np.float64) for name, value in variables.items()}

    def conv_bn(x, name, stride=1, relu=True):
        x = tf_conv(x, v[f"{name}/weights"], stride)
        scale = v[f"{name}/BatchNorm/gamma"] / np.sqrt(v[f"{name}/BatchNorm/moving_variance"] + 1e-5)
        shift = v[f"{name}/BatchNorm/beta"] - v[f"{name}/BatchNorm/moving_mean"] * scale
        x = x * torch.from_numpy(scale)[:, None, None] + torch.from_numpy(shift)[:, None, None]
        return x.clamp(min=0) if relu else x

    image = torch.from_numpy((rgb.astype(np.float64) - 128.0) / 128.0).permute(2, 0, 1)[None]
    total = np.zeros(WHITEN_DIM)
    for scale in SCALES:
        size = (round(image.shape[2] * scale), round(image.shape[3] * scale))
        x = image if scale == 1.0 else F.interpolate(image, size=size, mode="bilinear", align_corners=False)
        x = conv_bn(x, "resnet_v1_101/conv1", stride=2)
        pads = (*tf_padding(x.shape[3], 3, 2), *tf_padding(x.shape[2], 3, 2))
        x = F.max_pool2d(F.pad(x, pads, value=float("-inf")), 3, 2)
        channels = 64
        for block, (count, depth, stride) in enumerate(zip(units, DEPTHS, STRIDES), start=1):
            for unit in range(1, count + 1):
                scope = f"resnet_v1_101/block{block}/unit_{unit}/bottleneck_v1"
                unit_stride = stride if unit == count else 1
                if channels == depth * 4:
                    shortcut = x[:, :, ::unit_stride, ::unit_stride]
                else:
                    shortcut = conv_bn(x, f"{scope}/shortcut", unit_stride, relu=False)
                residual = conv_bn(x, f"{scope}/conv1")
                residual = conv_bn(residual, f"{scope}/conv2", unit_stride)
                residual = conv_bn(residual, f"{scope}/conv3", relu=False)
                x = (shortcut + residual).clamp(min=0)
                channels = depth * 4
        pooled = (x[0].numpy().clip(1e-6) ** 3).mean(axis=(1, 2)) ** (1 / 3)
        descriptor = pooled @ v["whitening/weights"] + v["whitening/biases"]
        total += descriptor / np.linalg.norm(descriptor)
    return total / np.linalg.norm(total)


@pytest.fixture(scope="module")
def variables():
    return slim_variables(np.random.default_rng(0), RESNET_101)


def image_set(folder: Path, rgb: np.ndarray) -> ImageSet:
    Image.fromarray(rgb).save(folder / "image.png")
    camera = Camera("PINHOLE", rgb.shape[1], rgb.shape[0], (50.0, 50.0, rgb.shape[1] / 2, rgb.shape[0] / 2))
    return ImageSet(["image.png"], folder, [camera], [[1.0, 0, 0, 0]], [[0.0, 0, 0]])


def test_tf_variables_give_the_tensorflow_forward_pass(tmp_path):
    variables = slim_variables(np.random.default_rng(0), SHALLOW)
    variables_file = tmp_path / "r101delg_variables.npz"
    np.savez(variables_file, **variables)
    rgb = np.random.default_rng(1).integers(0, 256, size=(60, 80, 3), dtype=np.uint8)
    options = dict(units=SHALLOW, whiten_dim=WHITEN_DIM, max_side=64)
    model = zoo_model("delg", weights=variables_file, **options)
    descriptors = model.describe(image_set(tmp_path, rgb))
    shrunk = np.asarray(Image.fromarray(rgb).resize((64, 48), Image.Resampling.BILINEAR))  # DELF's ResizeImage
    np.testing.assert_allclose(descriptors[0], reference_delg(shrunk, variables, SHALLOW), atol=1e-5)
    assert model.preprocessing.scales == SCALES and model.identity()["architecture"]["units"] == list(SHALLOW)

    converted = tmp_path / "delg.pt"
    convert_delg(variables_file, converted)
    again = zoo_model("delg", weights=converted, **options)
    np.testing.assert_array_equal(again.describe(image_set(tmp_path, rgb)), descriptors)


def test_resnet_v1_101_variables_fill_the_whole_network(variables, tmp_path):
    path = tmp_path / "r101delg_variables.npz"
    np.savez(path, **variables)
    model = zoo_model("delg", weights=path, whiten_dim=WHITEN_DIM)
    parameters = sum(p.numel() for p in model.network.parameters())
    backbone = sum(v.size for k, v in variables.items() if "resnet_v1_101" in k and "moving" not in k)
    assert parameters == backbone + 2048 * WHITEN_DIM + WHITEN_DIM + 1  # + whitening and GeM's p


def test_whitening_found_by_shape_or_scope_and_as_a_1x1_convolution(variables):
    rng = np.random.default_rng(2)
    extra = {"DELG/other/kernel": rng.normal(size=(2048, 8)), "DELG/other/bias": rng.normal(size=8)}
    with pytest.raises(ValueError, match="whitening_scope"):
        delg_state_dict_from_tf({**variables, **extra})
    state = delg_state_dict_from_tf({**variables, **extra}, whitening_scope="whitening")
    np.testing.assert_array_equal(state["whitening.weight"].numpy(), variables["DELG/whitening/weights:0"].T)

    as_conv = dict(variables)
    as_conv["DELG/whitening/weights:0"] = variables["DELG/whitening/weights:0"].reshape(1, 1, 2048, WHITEN_DIM)
    state = delg_state_dict_from_tf(as_conv)
    np.testing.assert_array_equal(state["whitening.weight"].numpy(), variables["DELG/whitening/weights:0"].T)
    assert state["backbone.block3.22.conv2.weight"].shape == (256, 256, 3, 3)
    assert state["backbone.block1.0.downsample.1.running_var"].shape == (256,)
    assert float(state["pooling.p"]) == 3.0


@pytest.mark.skipif(importlib.util.find_spec("tensorflow") is not None, reason="tensorflow is installed")
def test_savedmodel_without_tensorflow_says_how_to_get_it(tmp_path):
    (tmp_path / "r101delg_gldv2clean_20200914" / "variables").mkdir(parents=True)
    with pytest.raises(ImportError, match=r"locretrieval\[tensorflow\]"):
        read_tf_variables(tmp_path / "r101delg_gldv2clean_20200914")


def test_missing_file_names_the_expected_file_and_its_publisher(tmp_path):
    with pytest.raises(MissingWeightsError, match=r"r101delg_gldv2clean_20200914.*tensorflow/models"):
        zoo_model("delg", weights=tmp_path / "absent.pt")
