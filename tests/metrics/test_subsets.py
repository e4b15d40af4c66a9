import numpy as np
import pandas as pd
import pytest
from helpers import evaluate_config
from PIL import Image, ImageFilter

from locretrieval.config import ConfigError, validated
from locretrieval.metrics.subsets import (
    BLURRY,
    DYNAMIC_SCENE,
    MASKRCNN_WEIGHTS_FILE,
    MaskSource,
    SubsetSettings,
    blur_score,
    dynamic_category_ids,
    dynamic_fraction,
    image_subsets,
    load_maskrcnn,
    mask_source,
    maskrcnn_fractions,
    missing_mask_inputs,
    subset_masks,
    subset_scores,
)
from locretrieval.scene import Camera, ImageSet
from locretrieval.scene.images import read_image


def settings(*overrides: str) -> SubsetSettings:
    """The ``subsets`` group as ``evaluate.yaml`` composes it (its mask sources too), ``overrides`` applied."""
    cfg = evaluate_config("paths.root_dir=/nonexistent", "device=cpu", *overrides)
    return validated(SubsetSettings, cfg.subsets, "subsets")


CONFIG = settings()


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
    score = blur_score(np.repeat(board[..., None], 3, axis=2), CONFIG.blur_radius, CONFIG.blur_width)
    assert score == pytest.approx(20 * np.log(10), abs=1e-6)


def test_blur_score_orders_a_sharp_image_above_its_blurred_copy():
    sharp = textured()
    blurred = np.asarray(Image.fromarray(sharp).filter(ImageFilter.GaussianBlur(4)))
    radius, width = CONFIG.blur_radius, CONFIG.blur_width
    sharp_score, blurred_score = blur_score(sharp, radius, width), blur_score(blurred, radius, width)
    assert sharp_score > CONFIG.blur_threshold >= blurred_score
    resized = np.asarray(Image.fromarray(sharp).resize((1000, 600), Image.Resampling.NEAREST))
    assert width == 500 and blur_score(resized, radius, width) == pytest.approx(sharp_score, abs=1.0)  # at width 500


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
    cached = sorted((cache / "subsets").glob("*.npz"))
    assert len(cached) == 2  # blur scores and mask fractions
    stricter = settings("subsets.dynamic_fraction=0.05", "subsets.blur_threshold=-1e9")
    again, _ = image_subsets("toy", queries, stricter, cache_dir=cache)  # thresholds are not cache keys
    assert sorted((cache / "subsets").glob("*.npz")) == cached
    assert again[DYNAMIC_SCENE].tolist() == [True, True, False] and not again[BLURRY].any()


def test_mask_source_resolution(tmp_path):
    with_masks = image_set(tmp_path, [textured()], [np.zeros((4, 4), np.uint8)])
    without = image_set(tmp_path, [textured()])
    assert CONFIG.dynamic_masks == ["masks", "maskrcnn"]  # the first that serves every query
    assert mask_source(with_masks, CONFIG) == ("masks", CONFIG.mask_sources["masks"])
    assert mask_source(without, CONFIG) == ("none", None)
    weights = settings(f"subsets.mask_sources.maskrcnn.weights={tmp_path}/w.pth")
    assert mask_source(without, weights)[0] == "maskrcnn"
    assert missing_mask_inputs(without, weights) == [
        f"subsets.mask_sources.maskrcnn.weights: {tmp_path}/w.pth not found (torchvision's {MASKRCNN_WEIGHTS_FILE})"
    ]
    assert missing_mask_inputs(without, CONFIG) == []  # no mask source: no dynamic-scene subset
    assert missing_mask_inputs(without, settings("subsets.dynamic_masks=[masks]")) == [
        "subsets.dynamic_masks=[masks]: 1 of 1 images have no mask file (<kapture>/masks/<name>), e.g. 'q0.png'"
    ]  # the one source asked for
    (problem,) = missing_mask_inputs(without, settings("subsets.dynamic_masks=[maskrcnn]"))
    assert problem.startswith(
        f"subsets.dynamic_masks=[maskrcnn]: no weights (the path of torchvision's {MASKRCNN_WEIGHTS_FILE}"
    )
    with pytest.raises(
        ConfigError,
        match=r"subsets.dynamic_masks: \['sam'\] are not names of subsets.mask_sources \['masks', 'maskrcnn'\]",
    ):
        settings("subsets.dynamic_masks=[masks,sam]")
    with pytest.raises(ConfigError, match=r"subsets.mask_sources.maskrcnn.min_size: must be >= 32 pixels, got 8"):
        settings("subsets.mask_sources.maskrcnn.min_size=8")
    scores = subset_scores(without, CONFIG, None)
    assert scores["dynamic_fraction"].isna().all() and set(scores["mask_source"]) == {"none"}
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
        load_maskrcnn(tmp_path / MASKRCNN_WEIGHTS_FILE, "cpu", 800, 0.5)
    torch.manual_seed(0)
    # the layout of the published file: torchvision builds pretrained models with frozen batch norm
    backbone = resnet_fpn_backbone(
        backbone_name="resnet50", weights=None, norm_layer=FrozenBatchNorm2d, trainable_layers=3
    )
    state = MaskRCNN(backbone, num_classes=91).state_dict()
    weights = tmp_path / MASKRCNN_WEIGHTS_FILE
    torch.save(state, weights)
    model = load_maskrcnn(weights, "cpu", min_size=64, score_threshold=0.7)
    name = "roi_heads.box_predictor.cls_score.weight"
    assert torch.equal(model.state_dict()[name], state[name])
    assert model.transform.min_size == (64,) and model.roi_heads.score_thresh == 0.7 and not model.training
    queries = image_set(tmp_path, [textured(48, 64)])
    fractions = maskrcnn_fractions(queries, model, 0.5)
    assert fractions.shape == (1,) and 0.0 <= fractions[0] <= 1.0
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a state dict")
    with pytest.raises(ValueError, match="garbage.pth"):
        load_maskrcnn(garbage, "cpu", 800, 0.5)


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


class BrightPixels(MaskSource):
    """A mask source from outside the package: the pixels brighter than ``level``."""

    def __init__(self, level: int) -> None:
        self.level = level

    def unavailable(self, images):
        return None

    def key(self, images):
        return ["bright", self.level]

    def fractions(self, images):
        return np.array([(read_image(path).mean(-1) > self.level).mean() for path in images.paths])


def test_a_mask_source_from_outside_the_package_is_chosen_through_the_config(tmp_path, monkeypatch):
    chosen = settings(
        f"+subsets.mask_sources.bright={{_target_: {__name__}.BrightPixels, level: 128}}",
        "subsets.dynamic_masks=[bright]",
    )
    images = [textured(), np.full((300, 500, 3), 255, np.uint8)]
    queries = image_set(tmp_path, images, [np.zeros((10, 10), np.uint8)] * 2)  # mask files, not chosen
    subsets, table = image_subsets("toy", queries, chosen, cache_dir=tmp_path / "cache")
    expected = [(image.mean(-1) > 128).mean() for image in images]
    np.testing.assert_allclose(table["dynamic_fraction"], expected)
    assert set(table["mask_source"]) == {"bright"} and subsets[DYNAMIC_SCENE].tolist() == [e >= 0.2 for e in expected]


def test_a_tag_that_is_an_image_subset_is_that_subset_under_one_name(caplog):
    from locretrieval.metrics.subsets import known_subsets

    tags = {"all": np.ones(4, bool), "blur": np.array([1, 1, 0, 0], bool), "night": np.array([0, 0, 1, 1], bool)}
    images = {"blurry": np.array([0, 1, 1, 0], bool), "dynamic_scene": np.array([0, 0, 0, 1], bool)}
    table = pd.DataFrame({"blur_score": [5.0, 10.0, 15.0, 30.0], "blurry": images["blurry"]})
    with caplog.at_level("INFO"):
        tags_left, subsets, written = known_subsets(tags, images, table)
    assert set(tags_left) == {"all", "night"} and set(subsets) == {"blurry", "dynamic_scene"}  # no 'blur' beside it
    assert subsets["blurry"].tolist() == [True, True, False, False] == written["blurry"].tolist()
    assert subsets["dynamic_scene"].tolist() == [False, False, False, True]  # no 'dynamic' tag: the detector's
    assert written["blur_score"].tolist() == [5.0, 10.0, 15.0, 30.0] and table["blurry"].tolist() == [0, 1, 1, 0]
    assert "subset blurry: the 2 queries the scene tags 'blur' (the detector finds 2, 1 of them tagged)" in caplog.text


def test_a_scene_reports_each_subset_once_under_the_subsets_name(tmp_path):
    import dataclasses
    from types import SimpleNamespace

    from locretrieval.benchmark import scene_subsets

    blurred = np.asarray(Image.fromarray(textured()).filter(ImageFilter.GaussianBlur(4)))
    empty, full = np.zeros((10, 10), np.uint8), np.full((10, 10), 255, np.uint8)
    queries = image_set(tmp_path, [textured(), blurred, textured(), textured()], [empty, empty, empty, full])
    tags = [{"night"}, {"blur"}, {"blur"}, {"dynamic"}]  # the renderer blurred q1 and q2; q2 is sharp to the FFT
    queries = dataclasses.replace(queries, tags=[frozenset(t) for t in tags])
    subsets, table = scene_subsets(SimpleNamespace(name="toy", queries=queries), CONFIG, tmp_path / "cache")
    assert sorted(subsets) == ["all", "blurry", "dynamic_scene", "night"]  # no 'blur' nor 'dynamic' beside them
    assert subsets[BLURRY].tolist() == [False, True, True, False] == table[BLURRY].tolist()  # what the scene knows
    assert subsets[DYNAMIC_SCENE].tolist() == [False, False, False, True]
    assert table["blur_score"].iloc[2] > CONFIG.blur_threshold  # the detector alone would not count q2
