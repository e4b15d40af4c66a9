"""A trained network out of locretrieval as ONNX (``export.py 'export=[onnx]'``, `locretrieval.export.onnx`):
its descriptors under onnxruntime equal to torch's."""

import json
import logging
from pathlib import Path

import helpers
import numpy as np
import onnx
import onnxruntime
import pytest
import torch
from helpers import compose_config, export
from hydra.utils import instantiate
from networks import descriptors, lightning_checkpoint, small_model
from PIL import Image
from scipy.ndimage import gaussian_filter

from locretrieval.config import ConfigError
from locretrieval.errors import DataFileError
from locretrieval.export.onnx import NOT_NETWORKS, OnnxExportError, OnnxSettings, export_onnx
from locretrieval.models.files.weights import EMBEDDED_CHECKPOINT_KEY
from locretrieval.scene import Camera, ImageSet

ROOT = Path(__file__).resolve().parents[2]


def trained_lite0(path: Path, **options):
    """train.py's default model (EfficientNet-Lite0 + GeM, the package's ImageNet weights; ``options``
    over its keys) with a trained GeM exponent, and its checkpoint at ``path``."""
    model = helpers.zoo_model("lite0_gem", **options)
    with torch.no_grad():
        model.network.pooling.p.fill_(3.7)
    return model, lightning_checkpoint(model, path)


def test_a_trained_checkpoint_exports_with_a_dynamic_batch_and_image_size(tmp_path):
    model, checkpoint = trained_lite0(tmp_path / "last.ckpt")
    cfg = compose_config(
        "export", "export=[onnx]", "model=checkpoint", f"model.weights={checkpoint}", f"paths.root_dir={tmp_path}",
        *helpers.QUIET_EXTRACTION,
    )  # fmt: skip
    (path,) = export(cfg, tmp_path / "out")
    assert path == tmp_path / "out" / "trained.onnx" and not list((tmp_path / "out").glob(".*partial*"))
    graph = onnx.load(str(path))
    dims = [d.dim_param or d.dim_value for d in graph.graph.input[0].type.tensor_type.shape.dim]
    assert dims == ["batch", 3, "height", "width"]
    metadata = {entry.key: entry.value for entry in graph.metadata_props}
    assert metadata["mean"] == str([127 / 255] * 3) and metadata["max_side"] == "320"
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    generator = torch.Generator().manual_seed(1)
    images = torch.randn(5, 3, 160, 256, generator=generator)  # neither the traced batch nor size, nor the check's
    got = session.run(None, {"images": images.numpy()})[0]
    np.testing.assert_allclose(got, descriptors(model, images), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)


def photos(root: Path) -> ImageSet:
    """Three RGB photos of random blobs, 320 x 240, 240 x 320 and 150 x 100 px (not shrunk at 160)."""
    rng = np.random.default_rng(6)
    names = []
    for index, (width, height) in enumerate([(320, 240), (240, 320), (150, 100)]):
        pixels = gaussian_filter(rng.random((height, width, 3)), (4, 4, 0))
        names.append(f"photo{index}.png")
        Image.fromarray((255 * (pixels - pixels.min()) / np.ptp(pixels)).astype(np.uint8)).save(root / names[-1])
    sizes = [Image.open(root / name).size for name in names]
    cameras = [Camera("PINHOLE", w, h, (200.0, 200.0, w / 2, h / 2)) for w, h in sizes]
    return ImageSet(names, root, cameras, np.tile([1.0, 0, 0, 0], (3, 1)), np.zeros((3, 3)))


def network_input(path: Path, max_side: int, mean: list[float], std: list[float]) -> np.ndarray:
    """The ``[1, 3, H, W]`` input a user builds from the ONNX file's metadata: RGB, its longer side
    shrunk to ``max_side`` by PIL's bilinear filter, ``(rgb / 255 - mean) / std``."""
    image = Image.open(path).convert("RGB")
    scale = min(1.0, max_side / max(image.size))
    if scale < 1:
        image = image.resize((round(image.width * scale), round(image.height * scale)), Image.Resampling.BILINEAR)
    pixels = (np.asarray(image, dtype=np.float32) / 255 - np.float32(mean)) / np.float32(std)
    return pixels.transpose(2, 0, 1)[None]


def test_onnx_hub_and_model_checkpoint_give_a_checkpoints_descriptors_at_its_trained_size(tmp_path, caplog):
    """A network trained at max_side 160 (not model=checkpoint's lite0_gem 320): the ONNX file's
    metadata, the hub entry and model=checkpoint all resize to 160 and normalise with its mean and
    std, and give the same descriptors of the same photos; a size given explicitly overrides, with
    a warning naming the trained one."""
    _, checkpoint = trained_lite0(tmp_path / "last.ckpt", max_side=160)
    images = photos(tmp_path)
    trained = (
        "model=checkpoint",
        f"model.weights={checkpoint}",
        f"paths.root_dir={tmp_path}",
        *helpers.QUIET_EXTRACTION,
    )
    with caplog.at_level(logging.WARNING):
        (onnx_path,) = export(compose_config("export", "export=[onnx]", *trained), tmp_path / "out")
        evaluated = instantiate(helpers.evaluate_config(*trained).model).describe(images)
        network = torch.hub.load(str(ROOT), "locretrieval", weights=str(checkpoint), source="local")
    assert "trained at" not in caplog.text
    metadata = {entry.key: entry.value for entry in onnx.load(str(onnx_path)).metadata_props}
    metadata = {key: json.loads(metadata[key]) for key in ("max_side", "mean", "std", "size", "scales")}
    assert metadata["max_side"] == 160 and metadata["size"] is None and metadata["scales"] == [1.0]
    assert network.preprocessing.max_side == 160
    assert metadata["mean"] == [127 / 255] * 3 and metadata["std"] == [128 / 255] * 3  # Lite0's, not ImageNet's
    session = onnxruntime.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    inputs = [network_input(path, 160, metadata["mean"], metadata["std"]) for path in images.paths]
    assert [x.shape[2:] for x in inputs] == [(120, 160), (160, 120), (100, 150)]
    from_onnx = np.concatenate([session.run(None, {"images": x})[0] for x in inputs])
    with torch.no_grad():
        from_hub = np.concatenate([network(torch.from_numpy(x)).numpy() for x in inputs])
    np.testing.assert_allclose(from_onnx, evaluated, atol=1e-5)
    np.testing.assert_allclose(from_hub, evaluated, atol=1e-5)
    assert float((evaluated[0] * evaluated[1]).sum()) < 0.999  # the photos' descriptors differ

    caplog.clear()
    with caplog.at_level(logging.WARNING):
        overridden = instantiate(helpers.evaluate_config(*trained, "model.max_side=320").model)
        hub = torch.hub.load(str(ROOT), "locretrieval", weights=str(checkpoint), max_side=320, source="local")
    assert overridden.preprocessing.max_side == 320 == hub.preprocessing.max_side
    assert caplog.text.count("model.max_side=320 differs from 160, what the network in") == 2
    with pytest.raises(
        ValueError, match=r"model.max_side=checkpoint takes the value a locretrieval checkpoint records"
    ):
        helpers.zoo_model("lite0_gem", max_side="checkpoint")
    content = torch.load(checkpoint, weights_only=True)
    content[EMBEDDED_CHECKPOINT_KEY]["preprocessing"]["max_side"] = "all"
    torch.save(content, tmp_path / "damaged.ckpt")
    with pytest.raises(DataFileError, match=r"damaged.ckpt: its preprocessing max_side='all' is not a setting"):
        torch.hub.load(str(ROOT), "locretrieval", weights=str(tmp_path / "damaged.ckpt"), source="local")


def test_a_network_without_a_dynamic_image_size_exports_at_a_fixed_one(tmp_path):
    model = small_model("mixvpr")  # adaptive pooling to its grid: traced, the grid needs the input's size
    with pytest.raises(OnnxExportError, match=r"adaptive_avg_pool2d.*set onnx.size=\[width,height\]"):
        export_onnx(model, tmp_path / "mixvpr.onnx", OnnxSettings(18, None, 1e-4))
    assert not any(tmp_path.iterdir())
    path = export_onnx(model, tmp_path / "mixvpr.onnx", OnnxSettings(18, [224, 224], 1e-4))  # a 7 x 7 map: its grid
    images = torch.randn(4, 3, 224, 224, generator=torch.Generator().manual_seed(2))
    got = onnxruntime.InferenceSession(str(path)).run(None, {"images": images.numpy()})[0]
    np.testing.assert_allclose(got, descriptors(model, images), atol=1e-5)


def test_a_graph_that_fixed_the_batch_is_refused_and_not_kept(tmp_path):
    model = small_model("boq")  # its attention reshapes traced at the example's batch of 2
    with pytest.raises(OnnxExportError, match=r"fails on a 3 x 3 x 96 x 128 batch .*fixed the batch size"):
        export_onnx(model, tmp_path / "boq.onnx", OnnxSettings(18, [128, 96], 1e-4))
    assert not any(tmp_path.iterdir())


def test_onnx_export_refuses_a_model_that_is_not_a_torch_network(tmp_path):
    cfg = compose_config("export", "export=[onnx]", f"paths.root_dir={tmp_path}")  # DenseVLAD
    with pytest.raises(ConfigError, match=r"model 'densevlad' \(DenseVLAD\) is not a torch network"):
        export(cfg, tmp_path / "out")


def test_the_models_named_as_no_torch_network_are_those_whose_class_is_none():
    from hydra import compose, initialize_config_dir
    from hydra.utils import get_class

    from locretrieval.models.torch_descriptor import TorchGlobalDescriptor

    names = sorted(path.stem for path in (helpers.CONFIGS / "model").glob("*.yaml"))
    with initialize_config_dir(config_dir=str(helpers.CONFIGS), version_base="1.3"):
        targets = {name: compose("export", overrides=[f"model={name}"]).model._target_ for name in names}
    networks = {name for name, target in targets.items() if issubclass(get_class(target), TorchGlobalDescriptor)}
    assert sorted(set(names) - networks) == sorted(NOT_NETWORKS)
