"""Training: relevance from the ground truth, relevance-driven batches, the Lightning module and
the localization-validation callback, and train.py end to end through Hydra."""

import dataclasses
import re
from pathlib import Path

import helpers
import numpy as np
import pandas as pd
import pytest
import torch
from helpers import train
from hydra.utils import instantiate
from omegaconf import OmegaConf
from torchvision.transforms import v2
from training_runs import METRIC, SCENE, TINY_TRAINING, train_config

from locretrieval import geometry
from locretrieval.benchmark import benchmark, build_rankings, relevances
from locretrieval.build import benchmark_settings
from locretrieval.config import ConfigError, validated
from locretrieval.frusta import TruncatedFrusta, pairwise_overlap_radii
from locretrieval.groundtruth import DefinitionContext, GroundTruthSettings, RankedRelevance, compute_groundtruths
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset
from locretrieval.training.callbacks import TRAINED, every_validation_metrics, metric_rows
from locretrieval.training.data import RelevanceBatchSampler, TrainingAugmentation
from locretrieval.training.relevance import (
    NegativesRule,
    NotRelevantNegatives,
    TrainingRelevanceSettings,
    UnrelatedNegatives,
    combined_pairs,
    training_pairs,
)
from locretrieval.training.run import ValidationScope

RELATIVE_POSE = TrainingRelevanceSettings(
    {
        "_target_": "locretrieval.groundtruth.RelativePoseDefinition",
        "position_threshold": 10.0,
        "rotation_threshold": 30.0,
        "ranked": "within_thresholds",
    },
    UnrelatedNegatives(0.1, None, None),
)
AT_25M = DefinitionContext(far=25.0)


def negatives(rule=None, **changes):
    """`RELATIVE_POSE` with another negatives ``rule``, or its rule with other settings."""
    return dataclasses.replace(RELATIVE_POSE, negatives=rule or dataclasses.replace(RELATIVE_POSE.negatives, **changes))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("training_scene")
    render_synthetic_dataset(helpers.render_settings(SCENE), root)
    return load_kapture_scene("tiny", [root / "mapping"], [root / "query"], frustum_far=25.0)


def test_relative_pose_training_pairs_against_a_direct_computation(scene):
    database = scene.database
    pairs = training_pairs(database, RELATIVE_POSE, AT_25M)
    position = geometry.position_errors(database.centers[:, None], database.centers[None])
    rotation = geometry.rotation_errors_deg(database.qvec[:, None], database.qvec[None])
    relevant = (position < 10.0) & (rotation < 30.0)
    np.fill_diagonal(relevant, False)
    graded = pairs.graded.toarray()
    np.testing.assert_array_equal(graded > 0, relevant)
    expected = 1 - (position / 10.0 + rotation / 30.0) / 2
    np.testing.assert_allclose(graded[relevant], expected[relevant], rtol=1e-6)
    frusta = TruncatedFrusta.of_images(database, np.arange(len(database)), 0.1, 25.0)
    overlap = pairwise_overlap_radii(frusta, frusta) > 0
    np.testing.assert_array_equal(pairs.related.toarray(), overlap | relevant)
    assert relevant.any() and (~overlap).any()  # both positives and surely unrelated pairs exist
    strict = training_pairs(database, negatives(NotRelevantNegatives()), AT_25M)
    np.testing.assert_array_equal(strict.related.toarray(), relevant)  # every pair not relevant may be a negative
    facing = training_pairs(database, negatives(max_rotation=90.0), AT_25M)
    np.testing.assert_array_equal(facing.related.toarray(), (overlap & (rotation <= 90.0)) | relevant)
    assert (overlap & (rotation > 90.0)).any()  # views facing each other share frustum volume: now negatives


def test_batches_hold_anchors_with_positives_and_only_surely_unrelated_negatives(scene):
    pairs = training_pairs(scene.database, RELATIVE_POSE, AT_25M)
    sampler = RelevanceBatchSampler(pairs, anchors=4, positives=1, negatives=4, batches_per_epoch=5, seed=0)
    batches = list(sampler)
    assert len(batches) == 5 and all(len(b) == 12 for b in batches)
    graded, related = pairs.graded.toarray(), pairs.related.toarray()
    for batch in batches:
        anchors, positives, negatives = batch[:4], batch[4:8], batch[8:]
        assert all(graded[a, p] > 0 for a, p in zip(anchors, positives))
        # each negative is unrelated to the anchor it was drawn for (some anchor of the batch)
        assert all(any(not related[a, n] and a != n for a in anchors) for n in negatives)
        relevance, negative_mask = pairs.batch(np.array(batch))
        assert not (negative_mask & (relevance > 0)).any() and not np.diag(negative_mask).any()
    assert list(sampler) == batches  # the same epoch draws the same batches
    sampler.set_epoch(1)
    assert list(sampler) != batches
    hard = {
        int(a): np.array([n for n in range(pairs.num_images) if not related[a, n] and n != a][:2])
        for a in sampler.anchors
    }
    sampler.set_hard_negatives(hard)
    for batch in sampler:
        assert all(any(n in hard[a] for a in batch[:4]) for n in batch[8:])


def test_several_positives_per_anchor_are_distinct_relevant_images_in_anchor_order(scene):
    pairs = training_pairs(scene.database, RELATIVE_POSE, AT_25M)
    sampler = RelevanceBatchSampler(pairs, anchors=4, negatives=2, batches_per_epoch=5, seed=0, positives=3)
    graded = pairs.graded.toarray()
    for batch in sampler:
        assert len(batch) == 4 + 4 * 3 + 2
        for index, anchor in enumerate(batch[:4]):
            positives = batch[4 + 3 * index : 4 + 3 * (index + 1)]
            assert all(graded[anchor, p] > 0 for p in positives)
            assert len(set(positives)) == min(3, int((graded[anchor] > 0).sum()))  # all of them when fewer exist
    with pytest.raises(ValueError, match="positives"):
        RelevanceBatchSampler(pairs, anchors=4, negatives=2, batches_per_epoch=5, seed=0, positives=0)


#: `TrainingAugmentation` settings that change nothing (each test switches one transform on).
NO_AUGMENTATION = dict(
    zoom_probability=0.0,
    zoom=[1.0, 1.0],
    brightness=0.0,
    contrast=0.0,
    saturation=0.0,
    hue=0.0,
    low_light_probability=0.0,
    low_light_brightness=[0.25, 0.25],
    blur_probability=0.0,
    blur_sigma=[1.0, 1.0],
    noise_probability=0.0,
    noise_sigma=0.1,
)


def augmented(settings: dict, image: torch.Tensor) -> torch.Tensor:
    """``image [3, H, W]`` through `TrainingAugmentation.augment` (a batch of one)."""
    return TrainingAugmentation(**settings).augment(image[None])[0]


def per_image_reference(settings: TrainingAugmentation) -> v2.Transform:
    """The same augmentations as torchvision's per-image transforms (how 0.10 applied them, each
    image in a DataLoader worker): the reference distributions."""
    return v2.Compose(
        [
            v2.RandomApply(
                [v2.RandomAffine(degrees=0.0, scale=tuple(settings.zoom), interpolation=v2.InterpolationMode.BILINEAR)],
                p=settings.zoom_probability,
            ),
            v2.ColorJitter(settings.brightness, settings.contrast, settings.saturation, settings.hue),
            v2.RandomApply(
                [v2.ColorJitter(brightness=tuple(settings.low_light_brightness))], p=settings.low_light_probability
            ),
            v2.RandomApply([v2.GaussianBlur(9, tuple(settings.blur_sigma))], p=settings.blur_probability),
            v2.RandomApply(
                [
                    v2.ToDtype(torch.float32, scale=True),
                    v2.GaussianNoise(sigma=settings.noise_sigma),
                    v2.ToDtype(torch.uint8, scale=True),
                ],
                p=settings.noise_probability,
            ),
        ]
    )


def image_statistics(images: torch.Tensor) -> dict[str, np.ndarray]:
    """Per image: mean intensity, contrast (std of the grey image), saturation (channel spread),
    sharpness (mean absolute horizontal gradient) and the width of the bright central square."""
    values = images.float() / 255
    grey = values.mean(1)
    return {
        "brightness": values.mean((1, 2, 3)).numpy(),
        "contrast": grey.std((1, 2)).numpy(),
        "saturation": (values.amax(1) - values.amin(1)).mean((1, 2)).numpy(),
        "sharpness": (grey[:, :, 1:] - grey[:, :, :-1]).abs().mean((1, 2)).numpy(),
        "square": (grey[:, grey.shape[1] // 2] > 0.5).float().sum(1).numpy(),
    }


def test_batch_augmentation_draws_the_distributions_of_the_per_image_transforms():
    """Each image of a batch its own draw: 1,000 copies of one textured image through the batch
    augmentation (kornia) and through torchvision's per-image transforms give the same
    distributions of brightness, contrast, saturation, sharpness and zoom (two-sample KS tests)."""
    from scipy.stats import ks_2samp

    settings = TrainingAugmentation(
        **{
            **NO_AUGMENTATION,
            "zoom_probability": 0.5,
            "zoom": [1.0, 1.35],
            "brightness": 0.3,
            "contrast": 0.3,
            "saturation": 0.2,
            "hue": 0.02,
            "low_light_probability": 0.3,
            "low_light_brightness": [0.15, 0.5],
            "blur_probability": 0.3,
            "blur_sigma": [0.5, 2.0],
            "noise_probability": 0.3,
            "noise_sigma": 0.03,
        }
    )
    rng = np.random.default_rng(0)
    image = torch.from_numpy(rng.integers(40, 120, (3, 48, 64), dtype=np.uint8))
    image[1] += 40
    image[2] += 80  # bluish: saturation to change
    image[0, :, ::4] = 30  # a red-free stripe pattern: colour, edges
    image[:, 16:32, 24:40] = 220  # the central square the zoom enlarges
    batch = image.expand(1000, -1, -1, -1).contiguous()
    torch.manual_seed(1)
    ours = image_statistics(settings.augment(batch))
    reference = per_image_reference(settings)
    theirs = image_statistics(torch.stack([reference(one) for one in batch]))
    for name in ours:
        assert ks_2samp(ours[name], theirs[name]).pvalue > 0.01, (name, ours[name].mean(), theirs[name].mean())
    assert ours["square"].std() > 0 and ours["brightness"].std() > 0.02  # each image drew its own zoom and light


def test_low_light_and_noise_augmentations_scale_the_brightness_and_add_noise_of_the_given_sigma():
    torch.manual_seed(0)
    image = torch.full((3, 64, 64), 160, dtype=torch.uint8)
    image[:, :, 32:] = 80
    plain = NO_AUGMENTATION
    assert torch.equal(augmented(plain, image), image)
    dark = augmented({**plain, "low_light_probability": 1.0}, image).float()
    np.testing.assert_allclose(dark.numpy(), 0.25 * image.float().numpy(), atol=1.0)
    noisy = augmented({**plain, "noise_probability": 1.0}, image).float() - image.float()
    assert abs(noisy.std().item() / 255 - 0.1) < 0.005 and abs(noisy.mean().item()) < 1.0
    with pytest.raises(ValueError, match="low_light_brightness: must be"):
        TrainingAugmentation(**{**plain, "low_light_brightness": [0.5, 1.5]})


def test_zoom_augmentation_scales_offsets_from_the_image_centre_by_its_factor():
    plain = {**NO_AUGMENTATION, "zoom_probability": 1.0, "zoom": [1.25, 1.25]}
    width, height, offset = 320, 240, 48  # an edge 48 px right of the centre column
    image = torch.zeros((3, height, width), dtype=torch.uint8)
    image[:, :, width // 2 + offset :] = 200
    image[:, height // 2 - 2 : height // 2 + 2, width // 2 - 2 : width // 2 + 2] = 255  # a centre mark
    zoomed = augmented(plain, image)
    assert zoomed.shape == image.shape
    first_bright = int((zoomed[0].float().mean(0) > 100).nonzero()[0])
    assert abs(first_bright - (width // 2 + 1.25 * offset)) <= 1  # a longer focal length: offsets x 1.25 (208 -> 220)
    assert zoomed[0, height // 2, width // 2] == 255  # the centre stays (same optical axis, same pose)
    assert torch.equal(augmented({**plain, "zoom_probability": 0.0}, image), image)
    with pytest.raises(ValueError, match="zoom: must be"):
        TrainingAugmentation(**{**plain, "zoom": [0.8, 1.2]})


def test_images_of_different_training_scenes_are_unrelated(scene):
    first, second = scene.database.subset(np.arange(12)), scene.database.subset(np.arange(12, 24))
    combined = combined_pairs([first, second], RELATIVE_POSE, [AT_25M, AT_25M])
    alone = [training_pairs(images, RELATIVE_POSE, AT_25M) for images in (first, second)]
    graded, related = combined.graded.toarray(), combined.related.toarray()
    np.testing.assert_array_equal(graded[:12, :12], alone[0].graded.toarray())
    np.testing.assert_array_equal(related[12:, 12:], alone[1].related.toarray())
    assert not graded[:12, 12:].any() and not related[:12, 12:].any() and not related[12:, :12].any()


@pytest.mark.smoke
def test_fast_dev_run_of_train_py_through_hydra_compose(tmp_path):
    cfg = train_config(tmp_path, "+trainer.fast_dev_run=true")
    validator = train(cfg, tmp_path / "run")
    epochs = sorted({entry["epoch"] for entry in validator.history})
    assert epochs == [-1, 0]  # before training, and after the one batch
    assert "val/approximation/ewb/k3/5m_10deg" in validator.history[0]
    assert (tmp_path / "run" / "validation.csv").exists() and (tmp_path / "run" / "report.md").exists()
    assert set(validator.reference) == {
        "densevlad",
        "gt_relative_pose",
        "gt_frustum",
        "random",
    }  # the reference rankings
    expected = every_validation_metrics(benchmark_settings(cfg), ["relative_pose", "frustum"])
    assert set(validator.history[1]) - {"epoch"} == set(expected)  # what checkpoints may monitor is what is logged


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    """``python train.py debug=quick`` (its checkpoint and logging choices) on the tiny scene, with
    every gallery query: ``(validation callback, run folder, its log lines)``."""
    import logging

    root = tmp_path_factory.mktemp("quick")
    records, logger = [], logging.getLogger("locretrieval")
    handler, level = logging.Handler(), logger.level
    handler.emit = lambda record: records.append(record.getMessage())
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        cfg = train_config(root, "debug=quick", "callbacks.localization_validation.gallery_queries=8")
        validator = train(cfg, root / "run")
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    return validator, root / "run", records


def test_the_gallery_of_fixed_validation_queries_is_logged_to_tensorboard_and_the_report_at_each_validation(
    quick_run,
):
    validator, run, _ = quick_run
    # the gallery of the same validation queries at each validation, in TensorBoard and the report
    from io import BytesIO

    from PIL import Image
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tensorboard" / "version_0"), size_guidance={"images": 0})
    events.Reload()
    logged = events.Images("val/gallery")
    assert len(logged) == 2  # before training and after the batch
    last = np.asarray(Image.open(BytesIO(logged[-1].encoded_image_string)).convert("RGB"))
    np.testing.assert_array_equal(last, validator.galleries["last"])
    assert len(validator.gallery_rows) == 6 and (run / "gallery_before.jpg").exists()  # the 6 queries of the tiny scene
    assert "![gallery at the last validation](gallery_last.jpg)" in (run / "report.md").read_text()


def test_a_quick_run_keeps_one_checkpoint_in_a_few_tens_of_megabytes_and_ends_naming_what_it_wrote(quick_run):
    """debug=quick keeps last.ckpt only (EfficientNet-Lite0, its Adam state and the validation's
    galleries: 44 MB, its weights stored once); caches stay in paths.cache_dir, none is copied in."""
    _, run, records = quick_run
    sizes = {path.relative_to(run).as_posix(): path.stat().st_size for path in run.rglob("*") if path.is_file()}
    assert [name for name in sizes if name.startswith("checkpoints/")] == ["checkpoints/last.ckpt"]
    assert sum(sizes.values()) < 50e6, sorted(sizes.items(), key=lambda item: -item[1])[:5]
    assert max(size for name, size in sizes.items() if name != "checkpoints/last.ckpt") < 5e6
    assert records[-3:] == [
        f"run folder: {run}",
        f"checkpoint, last: {run / 'checkpoints' / 'last.ckpt'}",
        f"report: {run / 'report.md'}",
    ]


def test_a_checkpoint_monitoring_a_metric_never_logged_fails_at_start_up_naming_those_logged(tmp_path):
    cfg = train_config(tmp_path, "callbacks.best_checkpoint.monitor=val/approximation/ewb/k4/5m_10deg")
    with pytest.raises(
        ConfigError,
        match=r"callbacks.best_checkpoint.monitor: 'val/approximation/ewb/k4/5m_10deg' is not logged at "
        r"every validation; .* the metrics are: .*val/approximation/ewb/k3/5m_10deg",
    ):
        train(cfg, tmp_path / "run")
    assert not (Path(cfg.paths.cache_dir) / "synthetic").exists()  # before the scene is rendered
    sfm_only = train_config(tmp_path, "callbacks.best_checkpoint.monitor=val/global_sfm/pnp/k5/0.25m_2deg")
    with pytest.raises(ConfigError, match="is not logged at every validation"):  # logged every sfm_every_n_epochs only
        train(sfm_only, tmp_path / "run")


def test_callback_metrics_equal_a_direct_benchmark_and_evaluate_reads_the_checkpoint(tmp_path):
    cfg = train_config(
        tmp_path, "callbacks.localization_validation.sfm_every_n_epochs=1", "paradigms.global_sfm.k=[1,3]"
    )
    validator = train(cfg, tmp_path / "run")
    logged = validator.history[-1]
    checkpoint = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert checkpoint.exists()
    # evaluate.py's path: the zoo model reads the Lightning checkpoint unchanged
    model_cfg = OmegaConf.merge(cfg.model, {"weights": str(checkpoint), "max_side": 96})
    model = instantiate(model_cfg)
    settings = benchmark_settings(cfg)
    scene = instantiate(cfg.data)
    groundtruths = compute_groundtruths(
        scene, validated(GroundTruthSettings, cfg.groundtruth, "groundtruth"), settings.sfm, cfg.paths.cache_dir
    )
    descriptors = describe_scene(model, scene, cache_dir=None)
    rankings = build_rankings(scene, {TRAINED: descriptors}, groundtruths, settings.retrieval, random_seed=None)
    result = benchmark(
        scene,
        rankings,
        settings,
        {"all": np.ones(len(scene.queries), bool)},
        cfg.paths.cache_dir,
        relevances(groundtruths, RankedRelevance()),
    )
    direct = metric_rows(result, TRAINED, settings.paradigms.ks())
    assert direct.keys() == {k for k in logged if k != "epoch"}
    for key, value in direct.items():
        assert logged[key] == pytest.approx(value, abs=1e-6), key
    assert any(key.startswith("val/global_sfm/") for key in direct)
    assert {"val/local_sfm/pnp/k5/0.25m_2deg", "val/local_sfm/pnp/k10/0.25m_2deg"} <= direct.keys()  # 2a by default too
    sfm_validations = [entry for entry in validator.history if "val/local_sfm/pnp/k10/0.25m_2deg" in entry]
    assert len(sfm_validations) >= 2  # before training and after the epoch


@pytest.mark.slow
def test_resuming_from_the_last_checkpoint_continues_the_same_curve(tmp_path, monkeypatch):
    common = ("~augmentation", "trainer.deterministic=true")
    straight = train(
        train_config(tmp_path / "straight", *common, "trainer.max_epochs=2"), tmp_path / "straight" / "run"
    )
    checkpoints = tmp_path / "straight" / "run" / "checkpoints"
    assert torch.load(checkpoints / "last.ckpt", weights_only=False)["epoch"] == 1  # the last epoch, whichever was best
    # Interrupted after its first epoch: the same run (max_epochs, hence the cosine schedule) as the straight one.
    first = train_config(
        tmp_path / "resumed",
        *common,
        "trainer.max_epochs=2",
        "+callbacks.interrupt={_target_: helpers.StopAfterEpoch, epoch: 0}",
    )
    assert [entry["epoch"] for entry in train(first, tmp_path / "resumed" / "run").history] == [-1, 0]
    last = tmp_path / "resumed" / "run" / "checkpoints" / "last.ckpt"
    resumed = train(
        train_config(tmp_path / "resumed", *common, "trainer.max_epochs=2", f"ckpt_path={last}"),
        tmp_path / "resumed" / "run",
    )
    assert [entry["epoch"] for entry in resumed.history] == [-1, 0, 1]  # the callback's history came back
    for expected, found in zip(straight.history, resumed.history):
        assert found.keys() == expected.keys()
        for key, value in expected.items():
            assert found[key] == pytest.approx(value, abs=1e-6), (expected["epoch"], key)


@pytest.mark.slow
def test_two_process_cpu_ddp_smoke_run(tmp_path):
    import subprocess
    import sys

    tiny = [f"data.render.{key}={value}" for key, value in SCENE.items() if key != "conditions"]
    tiny += [f"data.render.conditions.{key}={value}" for key, value in SCENE["conditions"].items()]
    command = [
        sys.executable,
        str(helpers.CONFIGS.parent / "train.py"),
        "trainer=ddp",
        "trainer.accelerator=cpu",
        "trainer.devices=2",
        f"paths.root_dir={tmp_path}",
        f"hydra.run.dir={tmp_path}/run",
        "device=cpu",
        *tiny,
        "model.max_side=96",
        *TINY_TRAINING,
        "trainer.max_epochs=1",
        "trainer.enable_progress_bar=false",
        "model/backbone=torchvision",
        "model.backbone.name=resnet18",
        "model.weights=null",
        "model.random_init=true",
        "logger={}",
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Initializing distributed: GLOBAL_RANK: 1, MEMBER: 2/2" in done.stderr + done.stdout
    assert (tmp_path / "run" / "checkpoints" / "last.ckpt").exists()
    history = pd.read_csv(tmp_path / "run" / "validation.csv")
    assert sorted(set(history["epoch"])) == [-1, 0]


def test_extra_rendered_scenes_are_trained_on_with_their_queries_and_never_the_validation_queries(tmp_path, scene):
    from locretrieval.build import extra_renders
    from locretrieval.training.run import TrainingSettings, training_worlds

    cfg = train_config(tmp_path, "training.extra_renders=[{seed: 7}]")
    validation_scene = instantiate(cfg.data)
    settings = validated(TrainingSettings, cfg.training, "training")
    worlds = training_worlds(validation_scene, settings, [], extra_renders(cfg, settings, validation_scene))
    assert all(len(world.queries) == 0 for world in worlds)
    sets = [world.database for world in worlds]
    assert [len(images) for images in sets] == [24, 30]  # the validation database; the other world's database + queries
    assert not set(validation_scene.queries.paths) & {p for images in sets for p in images.paths}
    pairs = combined_pairs(sets, RELATIVE_POSE, [AT_25M] * len(sets))
    graded = pairs.graded.toarray()
    assert graded[24:48, 48:].any()  # the extra scene's database and queries are paired with each other
    itself = train_config(tmp_path, f"training.extra_renders=[{{seed: {SCENE['seed']}}}]")
    with pytest.raises(ValueError, match="renders the validation scene itself"):
        settings = validated(TrainingSettings, itself.training, "training")
        training_worlds(validation_scene, settings, [], extra_renders(itself, settings, validation_scene))


def test_hard_negatives_set_during_an_epoch_apply_to_its_later_batches(scene):
    pairs = training_pairs(scene.database, RELATIVE_POSE, AT_25M)
    sampler = RelevanceBatchSampler(pairs, anchors=4, positives=1, negatives=4, batches_per_epoch=6, seed=0)
    hard_image = {
        int(a): np.array([i for i in range(pairs.num_images) if i != a and not pairs.related[a, i]][:1])
        for a in sampler.anchors
    }
    batches = iter(sampler)
    first = next(batches)
    sampler.set_hard_negatives(hard_image)
    for batch in batches:
        anchors, negatives = batch[:4], batch[8:]
        assert set(negatives) <= {int(hard_image[a][0]) for a in anchors}
    assert len(first) == 12


def test_hard_negatives_are_the_highest_ranked_unrelated_images_by_the_current_network(scene):
    from types import SimpleNamespace

    from locretrieval.models import NetworkDescriptor
    from locretrieval.models.extraction import ExtractionSettings, Preprocessing
    from locretrieval.models.networks import GeMPooling, RetrievalNet
    from locretrieval.training.callbacks import HardNegativeMining

    torch.manual_seed(0)
    network = RetrievalNet(
        torch.nn.Sequential(torch.nn.Conv2d(3, 16, 5, stride=2), torch.nn.ReLU()),
        GeMPooling(16, 3.0, trainable=True),
        16,
    )
    pairs = training_pairs(scene.database, RELATIVE_POSE, AT_25M)
    sampler = RelevanceBatchSampler(pairs, anchors=4, positives=1, negatives=4, batches_per_epoch=1, seed=0)
    preprocessing = Preprocessing(max_side=None, scales=(1.0,))
    extraction = ExtractionSettings("cpu", 8, 0, False, False, None)
    mining = HardNegativeMining(
        [scene.database], pairs, sampler, preprocessing, extraction, every_n_steps=5, per_anchor=3
    )
    module = SimpleNamespace(network=network)
    for step in (0, 3, 4):  # not a multiple of 5 (or the first step): nothing mined
        mining.on_train_batch_start(SimpleNamespace(global_step=step, global_rank=0, world_size=1), module, None, step)
    assert sampler.hard == {}
    mining.on_train_batch_start(SimpleNamespace(global_step=5, global_rank=0, world_size=1), module, None, 5)
    descriptors = NetworkDescriptor("check", network, preprocessing, extraction).describe(scene.database)
    related = pairs.related.toarray()
    for anchor in sampler.anchors:
        similarity = descriptors @ descriptors[anchor]
        allowed = [i for i in np.argsort(-similarity, kind="stable") if i != anchor and not related[anchor, i]]
        assert set(sampler.hard[int(anchor)].tolist()) == set(allowed[:3])


@pytest.mark.parametrize("frozen", [True, False])
def test_frozen_batch_norm_keeps_the_pretrained_statistics_while_the_weights_learn(tmp_path, frozen):
    from locretrieval.models.files.weights import EMBEDDED_CHECKPOINT_KEY

    cfg = train_config(tmp_path, f"module.freeze_batch_norm={frozen}")
    train(cfg, tmp_path / "run")
    trained = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)[EMBEDDED_CHECKPOINT_KEY][
        "state_dict"
    ]
    initial = instantiate(cfg.model).network.state_dict()
    statistics = [key for key in initial if key.endswith(("running_mean", "running_var"))]
    affine = [key.replace("running_mean", "weight") for key in statistics if key.endswith("running_mean")]
    assert len(statistics) > 50
    assert all(torch.equal(trained[key], initial[key]) for key in statistics) == frozen
    assert not all(torch.equal(trained[key], initial[key]) for key in affine)  # batch-norm scales learn either way


@pytest.mark.slow
def test_frozen_parameters_keep_their_pretrained_values(tmp_path):
    from locretrieval.models.files.weights import EMBEDDED_CHECKPOINT_KEY

    patterns = "module.frozen=['backbone.timm.conv_stem.*','backbone.timm.blocks.[0-3].*']"
    cfg = train_config(tmp_path, patterns)
    train(cfg, tmp_path / "run")
    trained = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)[EMBEDDED_CHECKPOINT_KEY][
        "state_dict"
    ]
    network = instantiate(cfg.model).network
    initial = dict(network.named_parameters())
    frozen = [
        name for name in initial if re.fullmatch(r"backbone\.timm\.(conv_stem|blocks\.[0-3])\..*", name)
    ]  # stages 0-3
    assert len(frozen) > 20
    assert all(torch.equal(trained[name], initial[name]) for name in frozen)
    assert not any(
        torch.equal(trained[name], initial[name])
        for name in ("backbone.timm.conv_head.weight", "backbone.timm.blocks.6.0.conv_pwl.weight")
    )
    with pytest.raises(ConfigError, match=r"module.frozen: 'backbone.trunk.\*' matches no parameter"):
        train(train_config(tmp_path / "bad", "module.frozen=['backbone.trunk.*']"), tmp_path / "bad" / "run")


def test_evaluation_mode_restores_each_layers_own_mode():
    from locretrieval.models.extraction import evaluation_mode

    network = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3), torch.nn.BatchNorm2d(4), torch.nn.Dropout()).train()
    network[1].eval()  # frozen batch norm in a training network
    with evaluation_mode(network):
        assert not any(layer.training for layer in network.modules())
    assert [layer.training for layer in network.modules()] == [True, True, False, True]


def test_a_diverging_run_stops_at_the_step_naming_the_loss_and_the_learning_rate(tmp_path):
    from locretrieval.training.module import TrainingDiverged

    cfg = train_config(tmp_path, "module.optimizer.lr=1e6", "trainer.max_epochs=3", "sampler.batches_per_epoch=3")
    with pytest.raises(
        TrainingDiverged,
        match=r"training diverged at step \d+ \(epoch \d\): (the loss is nan|the loss is inf|the gradient "
        r"of .* is not finite), learning rate \[.*\] \(module.optimizer.lr\); lower module.optimizer.lr",
    ):
        train(cfg, tmp_path / "run")
    for checkpoint in (tmp_path / "run" / "checkpoints").glob(
        "*.ckpt"
    ):  # what was saved before holds finite weights only
        state = torch.load(checkpoint, weights_only=False)["state_dict"]
        assert all(torch.isfinite(value).all() for value in state.values() if value.is_floating_point())


def test_an_output_dir_holding_a_link_out_of_it_is_refused_before_anything_is_written(tmp_path):
    """``output_dir`` may be another folder than Hydra's (which its callback checked)."""
    from locretrieval.errors import DataFileError

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").symlink_to(tmp_path / "victim.yaml")
    with pytest.raises(
        DataFileError, match=rf"^{run / 'config.yaml'}: a symbolic link to {tmp_path / 'victim.yaml'}, "
    ):
        train(train_config(tmp_path), run)
    assert not (tmp_path / "victim.yaml").exists() and sorted(path.name for path in run.iterdir()) == ["config.yaml"]


@pytest.mark.slow
def test_resuming_from_a_file_that_is_not_a_checkpoint_of_this_project_is_refused_before_any_work(tmp_path):
    from locretrieval.training.checkpoints import check_resume_checkpoint

    (tmp_path / "notes.txt").write_text("not a checkpoint")
    torch.save({"weights": torch.zeros(2)}, tmp_path / "other.pt")
    cases = {
        tmp_path / "absent.ckpt": r"ckpt_path: .*absent.ckpt not found",
        tmp_path / "notes.txt": r"ckpt_path: .*notes.txt is not a Lightning checkpoint of locretrieval's train.py \(",
        tmp_path / "other.pt": r"ckpt_path: .*other.pt is a PyTorch file but not a Lightning checkpoint",
    }
    for path, message in cases.items():
        cfg = train_config(tmp_path / path.stem, f"ckpt_path={path}")
        with pytest.raises((ValueError, FileNotFoundError), match=message) as error:
            train(cfg, tmp_path / path.stem / "run")
        assert "weights_only" not in str(error.value)
        assert not (tmp_path / path.stem / ".cache").exists()  # refused before the scene was rendered
    # a checkpoint of another architecture
    first = train_config(tmp_path / "first")
    train(first, tmp_path / "first" / "run")
    descriptor = instantiate(first.model)
    checkpoint = tmp_path / "first" / "run" / "checkpoints" / "last.ckpt"
    check_resume_checkpoint(checkpoint, descriptor.model, descriptor.architecture)
    with pytest.raises(
        ValueError, match=r"ckpt_path: .*last.ckpt.*resume with the model settings of the run that wrote it"
    ):
        check_resume_checkpoint(checkpoint, descriptor.model, {**descriptor.architecture, "whiten_dim": 64})


class Killed(Exception):
    """Stands for the kill of a process in the middle of a write."""


@pytest.mark.slow
def test_a_run_killed_while_writing_last_ckpt_keeps_the_previous_checkpoint_whole(tmp_path, monkeypatch):
    import errno
    import os
    import shutil

    from locretrieval.training.checkpoints import check_resume_checkpoint

    common = ("~augmentation", "trainer.max_epochs=2")
    train(
        train_config(tmp_path, *common, "+callbacks.interrupt={_target_: helpers.StopAfterEpoch, epoch: 0}"),
        tmp_path / "run",
    )
    last = tmp_path / "run" / "checkpoints" / "last.ckpt"
    before = last.read_bytes()
    assert torch.load(last, weights_only=False)["epoch"] == 0

    # The next write of last.ckpt dies half-way through putting its bytes in place, as a kill would while
    # a temporary file in /tmp (another file system, e.g. tmpfs) is copied over it.
    rename = os.rename

    def across_file_systems(source, destination, *args, **kwargs):
        if str(destination).endswith("last.ckpt"):
            raise OSError(errno.EXDEV, "Invalid cross-device link")
        return rename(source, destination, *args, **kwargs)

    def killed_half_way(source, destination, *args, **kwargs):  # shutil.move's copy when rename fails
        data = Path(source).read_bytes()
        Path(destination).write_bytes(data[: len(data) // 2])
        raise Killed

    monkeypatch.setattr(os, "rename", across_file_systems)
    monkeypatch.setattr(shutil, "copyfile", killed_half_way)
    original_save = torch.save

    def save_killed_half_way(content, target, *args, **kwargs):  # our writer: dies half-way through its temporary file
        if (
            isinstance(content, dict)
            and "epoch" in content
            and str(target).endswith(".ckpt")
            and ".last.ckpt." in str(target)
        ):
            original_save(content, target, *args, **kwargs)
            Path(target).write_bytes(Path(target).read_bytes()[:1000])
            raise Killed
        return original_save(content, target, *args, **kwargs)

    monkeypatch.setattr(torch, "save", save_killed_half_way)
    with pytest.raises(Killed):
        train(train_config(tmp_path, *common, f"ckpt_path={last}"), tmp_path / "run")
    monkeypatch.undo()
    assert last.read_bytes() == before  # the previous checkpoint, whole: resumable
    descriptor = instantiate(train_config(tmp_path).model)
    check_resume_checkpoint(last, descriptor.model, descriptor.architecture)
    assert not [path.name for path in last.parent.iterdir() if path.name.startswith(".")]  # no temporary file left


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["joblib_local", "submitit_local"])
def test_a_parallel_training_multirun_as_documented_shares_one_cache_without_corrupting_it(tmp_path, launcher):
    """docs/training.md's ``python train.py -m hydra/launcher=joblib_local loss=ap,triplet`` (and
    under submitit's local executor, as on SLURM), with the default worker counts (renderer,
    DataLoader, SfM) and as many overrides as a real sweep: two jobs at once on a cold cache render
    the scene once (the other job waits for it), share features, matches, maps and ground truths,
    get short job folders, and both validate exactly as a run alone on the finished cache does."""
    import subprocess
    import sys

    tiny = [f"data.render.{key}={value}" for key, value in SCENE.items() if key not in ("conditions", "workers")]
    tiny += [f"data.render.conditions.{key}={value}" for key, value in SCENE["conditions"].items()]
    common = [
        f"paths.root_dir={tmp_path}",
        f"paths.cache_dir={tmp_path}/cache",
        "device=cpu",
        *tiny,
        "model.max_side=96",
        *(override for override in TINY_TRAINING if not override.startswith("datamodule.num_workers")),
        "callbacks.localization_validation.sfm_every_n_epochs=1",
        "paradigms.global_sfm.k=[1,3]",
        "paradigms.local_sfm.k=[3]",
        "trainer.max_epochs=1",
        "trainer.enable_progress_bar=false",
        "~logger",
    ]
    command = [
        sys.executable,
        str(helpers.CONFIGS.parent / "train.py"),
        "-m",
        f"hydra/launcher={launcher}",
        "loss=ap,triplet",
        f"hydra.sweep.dir={tmp_path}/multirun",
        *common,
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=900, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    jobs = sorted(path.parent for path in (tmp_path / "multirun").glob("*/validation.csv"))
    assert [job.name.split("_")[0] for job in jobs] == ["0", "1"]
    assert all(len(job.name) <= 96 for job in jobs)  # 24 overrides: cut, with a hash
    logs = [(job / "train.log").read_text() for job in jobs]
    assert sum(log.count("rendering the synthetic scene") for log in logs) == 1  # one job rendered, the other read it
    if launcher == "joblib_local":  # the two jobs' console lines interleave in the terminal: each says its job
        lines = re.findall(r"^\[\d{4}-[^]]+\](\[job \d\])?\[locretrieval\.", done.stdout, re.M)
        assert set(lines) == {"[job 0]", "[job 1]"}, done.stdout[-3000:]
    alone = train(
        train_config(
            tmp_path / "alone",
            f"paths.cache_dir={tmp_path}/cache",
            "callbacks.localization_validation.sfm_every_n_epochs=1",
            "paradigms.global_sfm.k=[1,3]",
            "paradigms.local_sfm.k=[3]",
            "~logger",
        ),
        tmp_path / "alone" / "run",
    )
    before_training = {key: value for key, value in alone.history[0].items()}
    assert any(key.startswith("val/global_sfm/") for key in before_training) and any(
        key.startswith("val/local_sfm/") for key in before_training
    )
    for job in jobs:
        history = pd.read_csv(job / "validation.csv")
        first = history[history["epoch"] == -1].set_index("metric")["value"]
        assert set(first.index) == set(before_training) - {"epoch"}
        for key, value in first.items():
            assert value == pytest.approx(before_training[key], abs=1e-6), (job, key)

    # the multirun's summary (the Hydra callback at its end), and report.py's of the folder afterwards
    summary = pd.read_csv(tmp_path / "multirun" / "summary.csv")
    validations = [pd.read_csv(job / "validation.csv") for job in jobs]
    objectives = [table[(table["epoch"] >= 0) & (table["metric"] == METRIC)]["value"].max() for table in validations]
    assert summary["objective"].tolist() == objectives and summary["state"].tolist() == ["finished", "finished"]
    assert summary["overrides"].str.contains("loss=ap").tolist() == [True, False]
    assert summary["best"].tolist() == [objectives[0] >= objectives[1], objectives[0] < objectives[1]]
    gap = pd.read_csv(jobs[0] / "gap.csv").set_index("metric")
    for metric, row in gap.iterrows():
        assert summary.loc[0, f"{metric} trained"] == pytest.approx(row["trained"]), metric
    markdown = (tmp_path / "multirun" / "summary.md").read_text()
    assert "| loss=ap " in markdown and "(best)" in markdown and "nan" not in markdown.lower()
    report = subprocess.run(
        [sys.executable, str(helpers.CONFIGS.parent / "report.py"), str(tmp_path / "multirun"), "--output", "again"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
    )  # fmt: skip
    assert report.returncode == 0, report.stderr[-3000:]
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "again" / "summary.csv"), summary)


def test_the_gap_table_gives_the_share_of_the_gap_to_the_ground_truth_that_training_closed():
    from types import SimpleNamespace

    from training_runs import outcomes

    from locretrieval.metrics.uncertainty import default_uncertainty
    from locretrieval.report.training import TrainingReportSettings, gap_table

    p1, local, glob = "approximation/ewb/k3/5m_10deg", "local_sfm/pnp/k10/0.25m_2deg", "global_sfm/pnp/k5/0.25m_2deg"
    n = 50
    validations = [  # before training and two epochs; the SfM paradigms validated before training and at the last
        {p1: outcomes(10, n), local: outcomes(50, n), glob: outcomes(70, n)},
        {p1: outcomes(20, n)},
        {p1: outcomes(40, n), local: outcomes(60, n)},
    ]
    reference = {
        "densevlad": {p1: outcomes(20, n), local: outcomes(40, n)},
        "gt_relative_pose": {p1: outcomes(60, n), local: outcomes(100, n)},
        "gt_co_observation": {local: outcomes(80, n)},
    }
    validation = SimpleNamespace(
        outcomes=validations,
        reference_outcomes=reference,
        splits={"val": "all"},
        subsets={"all": np.ones(n, dtype=bool)},
        settings=SimpleNamespace(metrics=SimpleNamespace(uncertainty=default_uncertainty())),
    )
    report = validated(TrainingReportSettings, helpers.compose_config("train").report, "report")  # the default rows
    table = gap_table(validation, report).set_index("metric")
    assert list(table.index) == [p1, local]  # global SfM: validated once
    assert table.loc[p1, ["untrained", "trained", "densevlad", "groundtruth_value"]].tolist() == [10, 40, 20, 60]
    assert table.loc[p1, "gap_closed_pct"] == pytest.approx(100 * (40 - 20) / (60 - 20))
    assert table.loc[p1, "gap_closed_low_pct"] < 50 < table.loc[p1, "gap_closed_high_pct"]
    assert table.loc[local, "groundtruth"] == "gt_co_observation"  # 2a: the co-observation upper bound
    assert table.loc[local, "gap_closed_pct"] == pytest.approx(100 * (60 - 40) / (80 - 40))
    assert set(table["split"]) == {"all"} and set(table["num_queries"]) == {n}
    # the local SfM row: the ground truth below the baseline, a trained model below both: no gap to close
    reference["densevlad"][local] = outcomes(37.5 * 1.0, 16)
    reference["gt_co_observation"][local] = outcomes(31.25, 16)
    validations[0][local], validations[2][local] = outcomes(18.75, 16), outcomes(25.0, 16)
    validation.subsets = {"all": np.ones(16, dtype=bool)}
    for entries in (validations, [reference["densevlad"], reference["gt_relative_pose"]]):
        for entry in entries:
            entry[p1] = entry[p1][:16]
    below = gap_table(validation, report).set_index("metric").loc[local]
    assert np.isnan(below["gap_closed_pct"]) and below["gap_note"].startswith(
        "no gap to close: the ground truth (31.2 %) is below densevlad (37.5 %) on these 16 queries"
    )


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("sampler.anchors=abc", r"sampler.anchors: Value 'abc' of type 'str' could not be converted to Integer"),
        (
            "+sampler.anchor=3",
            r"sampler.anchor: unknown key; expected one of \['pairs', "
            r"'anchors', 'negatives', 'batches_per_epoch', 'seed', 'positives'\]",
        ),
        (
            "augmentation.brightness=abc",
            r"augmentation.brightness: Value 'abc' of type 'str' could not be converted to Float",
        ),
        (
            "callbacks.localization_validation.every_n_epochs=often",
            r"callbacks.localization_validation.every_n_epochs: Value 'often'",
        ),
        (
            "train_relevance.definition=relative_pose",
            r"train_relevance.definition: must be a mapping with a _target_, the definition's class",
        ),
    ],
)
def test_every_object_node_is_checked_by_its_full_key_before_the_scene_is_prepared(tmp_path, override, message):
    cfg = train_config(tmp_path, override)
    with pytest.raises(ConfigError, match=message):
        train(cfg, tmp_path / "run")
    assert not (Path(cfg.paths.cache_dir) / "synthetic").exists()


@pytest.mark.parametrize("frozen_backbone", [False, True])
def test_head_lr_scale_moves_the_head_that_much_faster_than_the_backbone(frozen_backbone):
    """Adam's first step moves every parameter by its group's learning rate (m / sqrt(v) = +-1)."""
    from functools import partial

    from locretrieval.models.networks import GeMPooling, RetrievalNet

    torch.manual_seed(0)
    trunk = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3, stride=2), torch.nn.ReLU())
    network = RetrievalNet(trunk, GeMPooling(8, 3.0, trainable=False), 8, whitening=torch.nn.Linear(8, 4))
    module = helpers.training_module(
        network,
        scheduler=partial(torch.optim.lr_scheduler.CosineAnnealingLR, T_max=4),
        frozen=["backbone.*"] if frozen_backbone else [],
        head_lr_scale=10.0,
    )
    optimizers = module.configure_optimizers()
    optimizer = optimizers["optimizer"]
    before = {name: p.detach().clone() for name, p in network.named_parameters()}
    network(torch.rand(2, 3, 16, 16)).pow(3).sum().backward()
    optimizer.step()
    steps = {name: (p.detach() - before[name]).abs() for name, p in network.named_parameters()}
    torch.testing.assert_close(steps["whitening.weight"], torch.full((4, 8), 1e-2), atol=1e-5, rtol=0)
    trunk_step = 0.0 if frozen_backbone else 1e-3
    torch.testing.assert_close(steps["backbone.0.weight"], torch.full((8, 3, 3, 3), trunk_step), atol=1e-6, rtol=0)
    assert [group["name"] for group in optimizer.param_groups] == (
        ["head"] if frozen_backbone else ["backbone", "head"]
    )
    optimizers["lr_scheduler"].step()  # the schedule keeps the ratio
    rates = {group["name"]: group["lr"] for group in optimizer.param_groups}
    assert rates["head"] == pytest.approx(1e-2 * (1 + np.cos(np.pi / 4)) / 2)
    if not frozen_backbone:
        assert rates["head"] == pytest.approx(10 * rates["backbone"])
    plain = helpers.training_module(network).configure_optimizers()
    assert len(plain.param_groups) == 1 and plain.param_groups[0]["lr"] == 1e-3  # scale 1: one group, as before 0.9.0
    with pytest.raises(ValueError, match="module.head_lr_scale must be positive"):
        helpers.training_module(network, head_lr_scale=0)
    with pytest.raises(
        ValueError, match="module.head_lr_scale=10.0 needs a network with a backbone .* Sequential has no 'backbone'"
    ):
        helpers.training_module(trunk, head_lr_scale=10.0)


def test_validation_on_a_seeded_subset_of_the_queries_with_capped_sfm_features(tmp_path):
    scope = ValidationScope(max_queries=4, seed=3, sfm_max_keypoints=200, budget_minutes=None, held_out=0.0)
    cfg = train_config(
        tmp_path,
        "training.validation.max_queries=4",
        "training.validation.seed=3",
        "training.validation.sfm_max_keypoints=200",
        "+trainer.fast_dev_run=true",
    )
    validator = train(cfg, tmp_path / "run")
    full = instantiate(cfg.data)
    expected = np.sort(np.random.default_rng(3).choice(len(full.queries), size=4, replace=False))
    assert validator.scene.queries.names == [
        full.queries.names[q] for q in expected
    ]  # the same queries at every validation
    assert validator.settings.sfm.features.max_keypoints == 200
    settings = scope.settings(benchmark_settings(cfg))
    assert (
        settings.sfm.features.max_keypoints == 200 and scope.scene(full).queries.names == validator.scene.queries.names
    )
    assert ValidationScope(None, 0, None, None, 0.0).scene(full) is full


class FakeClock:
    """A clock that SfM work advances by ``per_query`` seconds a query (and describing by nothing):
    `sfm_within_budget`'s chunks as a machine of that throughput would cut them."""

    def __init__(self, per_query: float) -> None:
        self.now, self.per_query, self.chunks = 0.0, per_query, []

    def __call__(self) -> float:
        return self.now

    def install(self, monkeypatch) -> None:
        import locretrieval.benchmark as core
        import locretrieval.training.callbacks as callbacks

        real = core.run_sfm

        def run_sfm(inputs, rankings, paradigms, shard=None, queries=None):
            if queries is not None:  # a chunk of the budgeted validation
                self.chunks.append(list(queries))
                self.now += self.per_query * len(queries)
            return real(inputs, rankings, paradigms, shard, queries)

        monkeypatch.setattr(core, "run_sfm", run_sfm)
        monkeypatch.setattr(core.time, "perf_counter", self)
        monkeypatch.setattr(callbacks.time, "perf_counter", self)


@pytest.mark.parametrize("minutes, reached", [(0.5, 3), (0.9, 6)])
def test_the_first_validation_settles_the_queries_the_budget_holds_and_every_validation_keeps_them(
    tmp_path, monkeypatch, minutes, reached
):
    """10 s a query (a fake clock): 0.5 min reach 1, then 2 more (the 20 s left hold 2) = 30 s; 0.9 min
    reach 1, then 2 (at most twice the last chunk), 2 (24 s left), 1 (4 s left: one at least) = all 6."""
    clock = FakeClock(per_query=10.0)
    clock.install(monkeypatch)
    import locretrieval.training.callbacks as callbacks

    validated_on = []
    real_benchmark = callbacks.benchmark
    monkeypatch.setattr(
        callbacks,
        "benchmark",
        lambda scene, *args: validated_on.append(scene.queries.names) or real_benchmark(scene, *args),
    )
    cfg = train_config(
        tmp_path,
        "callbacks.localization_validation.sfm_every_n_epochs=1",
        f"training.validation.budget_minutes={minutes}",
        "training.validation.seed=7",
        "paradigms.local_sfm.k=[2]",
        "paradigms.global_sfm.k=[1]",
        "trainer.max_epochs=2",
    )
    validator = train(cfg, tmp_path / "run")
    order = np.random.default_rng(7).permutation(6)
    sizes = [len(chunk) for chunk in clock.chunks]
    assert sizes == ([1, 2] if reached == 3 else [1, 2, 2, 1]) and [q for c in clock.chunks for q in c] == list(
        order[:reached]
    )
    names = [instantiate(cfg.data).queries.names[q] for q in np.sort(order[:reached])]
    assert validator.scene.queries.names == validator.validated_queries == names
    # references, then epochs -1, 0 and 1: every validation on the same queries
    assert len(validated_on) == 4 and all(queries == names for queries in validated_on)
    assert sorted({entry["epoch"] for entry in validator.history}) == [-1, 0, 1]


def test_a_budget_too_small_for_one_validation_query_is_a_clear_error(tmp_path, monkeypatch):
    FakeClock(per_query=10.0).install(monkeypatch)
    cfg = train_config(
        tmp_path, "callbacks.localization_validation.sfm_every_n_epochs=1", "training.validation.budget_minutes=0.1"
    )
    with pytest.raises(
        ConfigError,
        match=r"training.validation.budget_minutes: 0.1 min cannot hold one validation query: describing the 30 "
        r"validation images took 0.0 s and localizing 1 query 10.0 s",
    ):
        train(cfg, tmp_path / "run")
    assert not (tmp_path / "run" / "checkpoints").exists()  # before any training step


class TemperatureLoss(torch.nn.Module):
    """A loss with a parameter: ListNet-style cross-entropy at a learned temperature."""

    def __init__(self, temperature: float = 0.1) -> None:
        super().__init__()
        self.log_temperature = torch.nn.Parameter(torch.tensor(float(np.log(temperature))))

    def forward(self, descriptors, relevance, negatives):
        scores = descriptors @ descriptors.T / self.log_temperature.exp()
        target = relevance / relevance.sum(1, keepdim=True).clamp_min(1e-9)
        mask = (relevance > 0) | negatives
        logits = scores.masked_fill(~mask, -1e4)
        rows = relevance.sum(1) > 0
        return -(target * torch.log_softmax(logits, 1))[rows].sum(1).mean()


@pytest.mark.parametrize("head_lr_scale", [1.0, 10.0])
def test_the_parameters_of_a_loss_are_optimized(tmp_path, head_lr_scale):
    from functools import partial

    from locretrieval.models.networks import GeMPooling, RetrievalNet

    torch.manual_seed(0)
    network = RetrievalNet(
        torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3, stride=2), torch.nn.ReLU()), GeMPooling(8, 3.0, trainable=False), 8
    )
    loss = TemperatureLoss()
    module = helpers.training_module(network, loss, partial(torch.optim.Adam, lr=1e-2), head_lr_scale=head_lr_scale)
    optimizer = module.configure_optimizers()
    assert any(parameter is loss.log_temperature for group in optimizer.param_groups for parameter in group["params"])
    before = loss.log_temperature.item()
    relevance = torch.tensor([[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1], [0, 0, 1, 0]], dtype=torch.float32)
    module.batch_loss(
        (torch.randint(0, 255, (4, 3, 16, 16), dtype=torch.uint8), relevance, relevance == 0, torch.arange(4))
    ).backward()
    optimizer.step()
    assert loss.log_temperature.item() != before  # the loss learned (Adam: by the learning rate)
    assert abs(abs(loss.log_temperature.item() - before) - 1e-2) < 1e-4


def test_the_report_says_which_requested_gap_row_it_cannot_fill(tmp_path, caplog):
    cfg = train_config(
        tmp_path,
        "paradigms.approximation.k=[1,5]",
        "callbacks.localization_validation.sfm_every_n_epochs=null",
        "callbacks.best_checkpoint.monitor=val/approximation/ewb/k5/5m_10deg",
        "optimized_metric=val/approximation/ewb/k5/5m_10deg",
        "+trainer.fast_dev_run=true",
    )
    with caplog.at_level("WARNING"):
        train(cfg, tmp_path / "run")
    text = (tmp_path / "run" / "report.md").read_text()
    assert (
        "Requested row approximation/ewb/k3/5m_10deg (report.gap) "
        "is not filled: k=3 is not in paradigms.approximation.k [1, 5]." in text  # Markdown text: plain brackets
    )
    assert (
        "Requested row local_sfm/pnp/k10/0.25m_2deg (report.gap) is not filled: the SfM paradigms are not validated"
        in text
    )
    assert "report.gap row approximation/ewb/k3/5m_10deg cannot be filled" in caplog.text
    moved = train_config(
        tmp_path / "moved",
        "+trainer.fast_dev_run=true",
        "callbacks.localization_validation.sfm_every_n_epochs=null",
        "report.gap=[{paradigm: approximation, method: ewb, k: 1, "
        "threshold: [5.0, 10.0], groundtruths: [relative_pose]}]",
    )
    train(moved, tmp_path / "moved" / "run")
    gaps = pd.read_csv(tmp_path / "moved" / "run" / "gap.csv")
    assert list(gaps["metric"]) == ["approximation/ewb/k1/5m_10deg"] and list(gaps["groundtruth"]) == [
        "gt_relative_pose"
    ]
    wrong = train_config(tmp_path / "wrong", "report.baseline=netvlad")
    with pytest.raises(
        ConfigError,
        match=r"report.baseline: 'netvlad' is not a validation reference \(validation_references: \['densevlad'\]\)",
    ):
        train(wrong, tmp_path / "wrong" / "run")


def test_train_py_takes_a_step_with_a_pytorch_metric_learning_loss(tmp_path):
    validator = train(train_config(tmp_path, "loss=multi_similarity", "+trainer.fast_dev_run=true"), tmp_path / "run")
    assert [entry["epoch"] for entry in validator.history] == [-1, 0]


@dataclasses.dataclass
class FarApart(NegativesRule):
    """A negatives rule from outside the package: negatives are the pairs more than ``metres`` apart."""

    metres: float

    def covisible(self, images, context):
        return lambda rows: geometry.pairwise_position_errors(images.centers[rows], images.centers) <= self.metres


def test_a_negatives_rule_from_outside_the_package_is_chosen_through_the_config(scene, tmp_path, monkeypatch):
    node = f"{{_target_: {__name__}.FarApart, metres: 15.0}}"
    cfg = train_config(tmp_path, "~train_relevance.negatives", f"+train_relevance.negatives={node}")
    settings = validated(TrainingRelevanceSettings, cfg.train_relevance, "train_relevance")
    database = scene.database
    pairs = training_pairs(database, settings, AT_25M)
    distance = geometry.position_errors(database.centers[:, None], database.centers[None])
    np.testing.assert_array_equal(pairs.related.toarray(), (distance <= 15.0) | (pairs.graded.toarray() > 0))
    assert (distance > 15.0).any()
    chosen = train_config(tmp_path, "train_relevance/negatives=not_relevant").train_relevance
    assert validated(TrainingRelevanceSettings, chosen, "train_relevance").negatives == NotRelevantNegatives()


def test_the_training_report_escapes_every_name_it_writes(tmp_path):
    from types import SimpleNamespace

    from locretrieval.metrics.uncertainty import default_uncertainty
    from locretrieval.report.training import TrainingReportSettings, write_training_report

    hostile = "<img src=x onerror=alert(1)>"
    metric = "val/approximation/ewb/k3/5m_10deg"
    history = [{"epoch": -1, metric: 10.0}, {"epoch": 0, metric: 40.0}]
    reference = {"densevlad": {metric: 20.0}, "gt_relative_pose": {metric: 60.0}, hostile: {metric: 30.0}}
    validation = SimpleNamespace(
        history_table=lambda: pd.DataFrame(
            [(-1, metric, 10.0, 1.0, 30.0, 10), (0, metric, 40.0, 20.0, 60.0, 10)],
            columns=["epoch", "metric", "value", "low", "high", "num_queries"],
        ),
        outcome_table=lambda: pd.DataFrame(columns=["ranking", "epoch", "metric", "query", "split", "localized"]),
        resolution=lambda: f"10 queries selected on {hostile}",
        history=history,
        reference=reference,
        reference_details={},
        galleries={},
        outcomes=[],
        reference_outcomes={},
        splits={"val": "all"},
        subsets={"all": np.ones(10, dtype=bool)},
        settings=SimpleNamespace(metrics=SimpleNamespace(uncertainty=default_uncertainty())),
    )
    report = validated(TrainingReportSettings, helpers.compose_config("train").report, "report")
    write_training_report(validation, tmp_path, report, {"val/local_sfm/pnp/k10/0.25m_2deg": hostile})
    text = (tmp_path / "report.md").read_text()
    # the resolution line, the reference row and the unfilled row
    assert "<img" not in text and text.count("&#60;img src=x onerror=alert(1)&#62;") == 3
    assert "| val/approximation/ewb/k3/5m_10deg " in text  # names without markup unchanged
