import numpy as np
import pytest
from PIL import Image, ImageFilter

from locretrieval.config import ConfigError, validated
from locretrieval.metrics.subsets import (
    BLURRY,
    DYNAMIC_SCENE,
    MASKRCNN_WEIGHTS_FILE,
    SubsetSettings,
    blur_score,
    dynamic_category_ids,
    dynamic_fraction,
    image_subsets,
    load_maskrcnn,
    maskrcnn_fractions,
    resolve_mask_source,
    subset_masks,
    subset_scores,
)
from locretrieval.scene import Camera, ImageSet

SETTINGS = {
    "enabled": True,
    "blur_threshold": 20.0,
    "blur_radius": 60,
    "blur_width": 500,
    "dynamic_fraction": 0.2,
    "mask_source": "auto",
    "maskrcnn_weights": None,
    "maskrcnn_min_size": 64,
    "maskrcnn_score_threshold": 0.5,
    "maskrcnn_mask_threshold": 0.5,
}
CONFIG = SubsetSettings(**SETTINGS)


def settings(**overrides) -> SubsetSettings:
    return validated(SubsetSettings, {**SETTINGS, **overrides}, "subsets")


def textured(height: int = 300, width: int = 500) -> np.ndarray:
    """A sharp RGB image: random blocks of several sizes (edges at every scale)."""
    rng = np.random.default_rng(0)
    layers = [
        np.kron(rng.random((-(-height // s), -(-width // s))), np.ones((s, s)))[:height, :width] for s in (1, 4, 20)
    ]
    gray = (255 * sum(layers) / len(layers)).astype(np.uint8)
    return np.repeat(gray[..., None], 3, axis=2)


def image_set(tmp_path, images: list[np.ndarray], masks: list[np.ndarray] | None = None) -> ImageSet:
    names, mask_paths = [], []
    for n, image in enumerate(images):
        Image.fromarray(image).save(tmp_path / f"q{n}.png")
        names.append(f"q{n}.png")
        if masks is not None:
            Image.fromarray(masks[n]).save(tmp_path / f"m{n}.png")
            mask_paths.append(tmp_path / f"m{n}.png")
    camera = Camera("SIMPLE_PINHOLE", 500, 300, (400.0, 250.0, 150.0))
    return ImageSet(
        names, tmp_path, [camera] * len(names), np.tile([1.0, 0, 0, 0], (len(names), 1)), np.zeros((len(names), 3)),
        mask_paths=mask_paths if masks is not None else None,
    )  # fmt: skip


def test_blur_score_of_a_pure_high_frequency_pattern_is_20_ln_amplitude():
    # a checkerboard around 128 has all its energy at the highest frequency, outside the
    # removed low-frequency square: the residual is +-10 everywhere
    rows, columns = np.indices((400, 500))
    board = (128 + 10 * (-1) ** (rows + columns)).astype(np.uint8)
    assert blur_score(np.repeat(board[..., None], 3, axis=2)) == pytest.approx(20 * np.log(10), abs=1e-6)


def test_blur_score_orders_a_sharp_image_above_its_blurred_copy():
    sharp = textured()
    blurred = np.asarray(Image.fromarray(sharp).filter(ImageFilter.GaussianBlur(4)))
    sharp_score, blurred_score = blur_score(sharp), blur_score(blurred)
    assert sharp_score > CONFIG.blur_threshold >= blurred_score
    resized = np.asarray(Image.fromarray(sharp).resize((1000, 600), Image.Resampling.NEAREST))
    assert blur_score(resized) == pytest.approx(sharp_score, abs=1.0)  # scored at width 500


def test_mask_subsets_threshold_inclusive_and_cached(tmp_path):
    masks = [np.zeros((10, 10), np.uint8) for _ in range(3)]
    masks[0][:2] = 255  # 20 %: a dynamic scene (>= 0.2)
    masks[1][:1] = 1  # 10 %
    images = [textured(), np.asarray(Image.fromarray(textured()).filter(ImageFilter.GaussianBlur(4))), textured()]
    queries = image_set(tmp_path, images, masks)
    cache = tmp_path / "cache"
    subsets, table = image_subsets("toy", queries, CONFIG, cache_dir=cache)
    assert subsets[DYNAMIC_SCENE].tolist() == [True, False, False]
    assert subsets[BLURRY].tolist() == [False, True, False]
    np.testing.assert_allclose(table["dynamic_fraction"], [0.2, 0.1, 0.0])
    assert set(table["mask_source"]) == {"masks"} and table["image"].tolist() == queries.names
    cached = sorted((cache / "subsets").iterdir())
    assert len(cached) == 2  # blur scores and mask fractions
    stricter = settings(dynamic_fraction=0.05, blur_threshold=-1e9)
    again, _ = image_subsets("toy", queries, stricter, cache_dir=cache)  # thresholds are not cache keys
    assert sorted((cache / "subsets").iterdir()) == cached
    assert again[DYNAMIC_SCENE].tolist() == [True, True, False] and not again[BLURRY].any()


def test_mask_source_resolution(tmp_path):
    with_masks = image_set(tmp_path, [textured()], [np.zeros((4, 4), np.uint8)])
    without = image_set(tmp_path, [textured()])
    assert resolve_mask_source(with_masks, CONFIG) == "masks"
    assert resolve_mask_source(without, CONFIG) == "none"
    assert resolve_mask_source(without, settings(maskrcnn_weights="w.pth")) == "maskrcnn"
    with pytest.raises(
        ConfigError, match=r"subsets.mask_source: must be one of \['auto', 'masks', 'maskrcnn', 'none'\], got 'sam'"
    ):
        settings(mask_source="sam")
    with pytest.raises(
        ConfigError, match=f"subsets.maskrcnn_weights: mask_source=maskrcnn needs .*{MASKRCNN_WEIGHTS_FILE}"
    ):
        settings(mask_source="maskrcnn")
    scores = subset_scores(without, CONFIG)
    assert scores["dynamic_fraction"].isna().all()
    assert set(subset_masks(scores, CONFIG)) == {BLURRY}  # no dynamic subset without masks


def test_dynamic_fraction_counts_the_pixels_of_dynamic_classes():
    import torch

    person, car, chair = 1, 3, 62
    ids = torch.as_tensor(dynamic_category_ids())
    assert {person, car} <= set(dynamic_category_ids()) and chair not in dynamic_category_ids()
    masks = torch.zeros((3, 1, 10, 10))
    masks[0, 0, :3] = 0.9  # person, 30 %
    masks[1, 0, 2:6] = 0.9  # chair: static
    masks[2, 0, 5:] = 0.9  # car, 50 %, overlapping nothing
    masks[0, 0, 9] = 0.4  # below the mask threshold
    assert dynamic_fraction(torch.tensor([person, chair]), masks[:2], ids, 0.5) == pytest.approx(0.3)
    assert dynamic_fraction(torch.tensor([person, chair, car]), masks, ids, 0.5) == pytest.approx(0.8)
    assert dynamic_fraction(torch.tensor([chair]), masks[1:2], ids, 0.5) == 0.0
    assert dynamic_fraction(torch.zeros(0, dtype=torch.int64), masks[:0], ids, 0.5) == 0.0


def test_maskrcnn_weights_are_loaded_from_a_local_torchvision_state_dict(tmp_path):
    import torch
    from torchvision.models.detection import MaskRCNN
    from torchvision.models.detection.backbone_utils import resnet_fpn_backbone
    from torchvision.ops.misc import FrozenBatchNorm2d

    with pytest.raises(FileNotFoundError, match=f"{MASKRCNN_WEIGHTS_FILE}.*download.pytorch.org"):
        load_maskrcnn(tmp_path / MASKRCNN_WEIGHTS_FILE)
    torch.manual_seed(0)
    # the layout of the published file: torchvision builds pretrained models with frozen batch norm
    backbone = resnet_fpn_backbone(
        backbone_name="resnet50", weights=None, norm_layer=FrozenBatchNorm2d, trainable_layers=3
    )
    state = MaskRCNN(backbone, num_classes=91).state_dict()
    weights = tmp_path / MASKRCNN_WEIGHTS_FILE
    torch.save(state, weights)
    model = load_maskrcnn(weights, min_size=64, score_threshold=0.7)
    name = "roi_heads.box_predictor.cls_score.weight"
    assert torch.equal(model.state_dict()[name], state[name])
    assert model.transform.min_size == (64,) and model.roi_heads.score_thresh == 0.7 and not model.training
    queries = image_set(tmp_path, [textured(48, 64)])
    fractions = maskrcnn_fractions(queries, model, 0.5)
    assert fractions.shape == (1,) and 0.0 <= fractions[0] <= 1.0
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a state dict")
    with pytest.raises(ValueError, match="garbage.pth"):
        load_maskrcnn(garbage)


def test_a_moved_dataset_and_cache_reuse_the_cached_mask_fractions(tmp_path, monkeypatch):
    import shutil

    from locretrieval.metrics import subsets as subsets_module

    first = tmp_path / "first"
    first.mkdir()
    queries = image_set(
        first, [textured(), textured()], [np.zeros((10, 10), np.uint8), np.full((10, 10), 255, np.uint8)]
    )
    _, table = image_subsets("toy", queries, CONFIG, cache_dir=first / "cache")
    moved = tmp_path / "moved"
    shutil.move(first, moved)  # images, masks and cache together, file times kept
    again = ImageSet(
        queries.names,
        moved,
        queries.cameras,
        queries.qvec,
        queries.tvec,
        mask_paths=[moved / p.name for p in queries.mask_paths],
    )
    monkeypatch.setattr(subsets_module, "mask_fractions", lambda images: pytest.fail("recomputed after a move"))
    monkeypatch.setattr(subsets_module, "blur_scores", lambda *args: pytest.fail("recomputed after a move"))
    _, moved_table = image_subsets("toy", again, CONFIG, cache_dir=moved / "cache")
    np.testing.assert_array_equal(moved_table["dynamic_fraction"], table["dynamic_fraction"])
