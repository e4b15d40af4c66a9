"""NetVLAD: the authors' struct .mat layout, MATLAB's flattening, an independent reference."""

from pathlib import Path

import numpy as np
import pytest
import scipy.io
import torch
from helpers import zoo_model
from PIL import Image

from locretrieval.models.files.weights import HASH_CACHE_ENV, MissingWeightsError
from locretrieval.models.networks import NetVLADPooling
from locretrieval.models.published.netvlad import convert_netvlad
from locretrieval.scene import Camera, ImageSet

#: VGG16 up to conv5_3 in MatConvNet's layer order ("M": 2x2 max-pool).
VGG16 = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
AVERAGE_RGB = np.array([122.675, 116.669, 104.008])


@pytest.fixture(autouse=True)
def hash_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(HASH_CACHE_ENV, str(tmp_path / "hashes"))


def cell(*arrays):
    out = np.empty((1, len(arrays)), dtype=object)
    for i, array in enumerate(arrays):
        out[0, i] = array
    return out


def write_struct_mat(path: Path, clusters: int, whiten_dim: int | None, seed: int = 0) -> dict:
    """A struct-form NetVLAD .mat as net_class2struct.m writes it, with small random weights."""
    rng = np.random.default_rng(seed)
    layers, convs, channels, block, index = [], [], 3, 1, 1
    for entry in VGG16:
        if entry == "M":
            layers.append({"name": f"pool{block}", "type": "pool", "weights": cell()})
            block, index = block + 1, 1
            continue
        w = (rng.normal(size=(3, 3, channels, entry)) * np.sqrt(2.0 / (9 * channels))).astype(np.float32)
        b = (rng.normal(size=(entry, 1)) * 0.01).astype(np.float32)
        layers.append({"name": f"conv{block}_{index}", "type": "conv", "weights": cell(w, b)})
        convs.append((w.astype(np.float64), b.reshape(-1).astype(np.float64)))
        layers.append({"name": f"relu{block}_{index}", "type": "relu", "weights": cell()})
        channels, index = entry, index + 1
    layers.pop()  # the network is cut at conv5_3, before its ReLU
    assign = rng.normal(size=(1, 1, 512, clusters)).astype(np.float32) * 3
    centres = rng.normal(size=(512, clusters)).astype(np.float32) * 0.05  # stored negated
    layers += [
        {"name": "preL2", "type": "normalize", "weights": cell()},
        {"name": "vlad:core", "type": "custom", "weights": cell(assign, centres)},
        {"name": "vlad:intranorm", "type": "custom", "weights": cell()},
        {"name": "vlad:L2", "type": "custom", "weights": cell()},
    ]
    parameters = {"convs": convs, "assign": assign[0, 0].astype(np.float64), "centres": centres.astype(np.float64)}
    if whiten_dim:
        wpca = (rng.normal(size=(1, 1, 512 * clusters, whiten_dim)) / np.sqrt(512 * clusters)).astype(np.float32)
        bias = (rng.normal(size=(whiten_dim, 1)) * 0.01).astype(np.float32)
        layers += [{"name": "WPCA", "type": "conv", "weights": cell(wpca, bias)}]
        parameters["wpca"] = (wpca[0, 0].astype(np.float64), bias.reshape(-1).astype(np.float64))
    layers += [{"name": "L2", "type": "custom", "weights": cell()}]
    struct_layers = np.empty((1, len(layers)), dtype=object)
    for i, layer in enumerate(layers):
        struct_layers[0, i] = layer
    average = AVERAGE_RGB.reshape(1, 1, 3).astype(np.float32)
    scipy.io.savemat(path, {"net": {"layers": struct_layers, "meta": {"normalization": {"averageImage": average}}}})
    return parameters


def conv_same(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3x3 'same' convolution of ``[C, H, W]`` with MatConvNet filters ``[S, S, IN, OUT]``."""
    _, height, width = x.shape
    padded = np.pad(x, ((0, 0), (1, 1), (1, 1)))
    out = np.zeros((w.shape[3], height, width))
    for dy in range(3):
        for dx in range(3):
            out += np.tensordot(w[dy, dx], padded[:, dy : dy + height, dx : dx + width], axes=([0], [0]))
    return out + b[:, None, None]


def reference_netvlad(rgb: np.ndarray, parameters: dict) -> np.ndarray:
    """The MATLAB network on one image, written out: VGG16 to conv5_3, then VLAD with loops."""
    x = (rgb.astype(np.float64) - AVERAGE_RGB).transpose(2, 0, 1)
    convs = iter(parameters["convs"])
    for position, entry in enumerate(VGG16):
        if entry == "M":
            c, h, w = x.shape
            x = x[:, : h // 2 * 2, : w // 2 * 2].reshape(c, h // 2, 2, w // 2, 2).max(axis=(2, 4))
            continue
        x = conv_same(x, *next(convs))
        if position < len(VGG16) - 1:
            x = np.maximum(x, 0)
    features = x.reshape(x.shape[0], -1)  # [D, N]
    assign, centres = parameters["assign"], -parameters["centres"]  # [D, K], true centres
    dim, clusters = assign.shape
    vlad = np.zeros((clusters, dim))  # MATLAB's K x D matrix
    for n in range(features.shape[1]):
        x_n = features[:, n] / np.linalg.norm(features[:, n])
        logits = assign.T @ x_n
        soft = np.exp(logits - logits.max())
        soft /= soft.sum()
        for k in range(clusters):
            vlad[k] += soft[k] * (x_n - centres[:, k])
    vlad /= np.linalg.norm(vlad, axis=1, keepdims=True)
    flat = vlad.flatten(order="F")  # MATLAB column-major: cluster index fastest
    flat /= np.linalg.norm(flat)
    if "wpca" in parameters:
        matrix, bias = parameters["wpca"]
        flat = flat @ matrix + bias
        flat /= np.linalg.norm(flat)
    return flat


def one_image_set(folder: Path, rgb: np.ndarray) -> ImageSet:
    Image.fromarray(rgb).save(folder / "image.png")
    height, width = rgb.shape[:2]
    camera = Camera("PINHOLE", width, height, (50.0, 50.0, width / 2, height / 2))
    return ImageSet(["image.png"], folder, [camera], [[1.0, 0, 0, 0]], [[0.0, 0, 0]])


@pytest.fixture(scope="module")
def struct_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("netvlad") / "Pitts30K_struct.mat"
    return path, write_struct_mat(path, clusters=4, whiten_dim=16)


def test_struct_mat_matches_the_matlab_network_written_out(struct_file, tmp_path):
    path, parameters = struct_file
    rgb = np.random.default_rng(1).integers(0, 256, size=(48, 64, 3), dtype=np.uint8)
    images = one_image_set(tmp_path, rgb)
    model = zoo_model("netvlad", weights=path, clusters=4, whiten_dim=16, max_side=None)
    descriptors = model.describe(images)
    assert descriptors.dtype == np.float32 and descriptors.shape == (1, 16)
    np.testing.assert_allclose(descriptors[0], reference_netvlad(rgb, parameters), atol=1e-5)
    assert model.identity()["architecture"] == {"clusters": 4, "whiten_dim": 16}
    np.testing.assert_allclose(model.preprocessing.mean, AVERAGE_RGB / 255, rtol=1e-6)

    converted = tmp_path / "netvlad.pt"
    convert_netvlad(path, converted)
    again = zoo_model("netvlad", weights=converted, clusters=4, whiten_dim=16, max_side=None)
    np.testing.assert_array_equal(again.describe(images), descriptors)


def test_vlad_flattening_is_matlab_column_major_of_the_cluster_by_dimension_matrix():
    rng = np.random.default_rng(2)
    dim, clusters = 3, 2
    pooling = NetVLADPooling(dim, clusters)
    assign, centres = rng.normal(size=(clusters, dim)), rng.normal(size=(clusters, dim))
    with torch.no_grad():
        pooling.assignment.weight.copy_(torch.from_numpy(assign).reshape(clusters, dim, 1, 1))
        pooling.centers.copy_(torch.from_numpy(centres))
    features = rng.normal(size=(dim, 2, 2))
    with torch.no_grad():
        flat = pooling(torch.from_numpy(features)[None].float())[0].double().numpy()

    x = features.reshape(dim, -1)
    x = x / np.linalg.norm(x, axis=0)
    soft = np.exp(assign @ x)
    soft /= soft.sum(axis=0)
    vlad = np.stack([(soft[k] * (x - centres[k][:, None])).sum(axis=1) for k in range(clusters)])  # K x D
    vlad /= np.linalg.norm(vlad, axis=1, keepdims=True)
    expected = np.array([vlad[k, d] for d in range(dim) for k in range(clusters)])  # MATLAB vlad(:)
    np.testing.assert_array_equal(expected, vlad.flatten(order="F"))
    np.testing.assert_allclose(flat, expected / np.linalg.norm(expected), atol=1e-6)


def test_configuration_must_match_the_file(struct_file):
    path, _ = struct_file
    with pytest.raises(
        ValueError, match=r"struct\.mat: architecture in the file differs from the configuration \(clusters: file"
    ):
        zoo_model("netvlad", weights=path, clusters=64, whiten_dim=4096)


def test_missing_file_names_the_expected_file_and_its_publisher(tmp_path):
    with pytest.raises(MissingWeightsError, match=r"Pitts30K_struct\.mat.*netvlad"):
        zoo_model("netvlad", weights=tmp_path / "absent.mat")


def test_class_form_mat_is_refused_with_a_hint(tmp_path):
    path = tmp_path / "vd16_pitts30k_conv5_3_vlad_preL2_intra_white.mat"
    scipy.io.savemat(path, {"net": np.zeros(3)})
    with pytest.raises(ValueError, match="net_class2struct"):
        zoo_model("netvlad", weights=path)
