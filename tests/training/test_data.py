"""The training data pipeline (`locretrieval.training.data`): relevance-driven batches and their hard
negatives, augmentations of the whole batch, images decoded once into a shared memory-mapped cache,
the device train.py picks, the DataLoader's processes."""

import multiprocessing
import os

import helpers
import numpy as np
import pytest
import torch
from decoding_jobs import decode_into
from omegaconf import OmegaConf
from PIL import Image
from torchvision.transforms import v2
from training_runs import AT_25M, RELATIVE_POSE

from locretrieval.config import trainer_accelerator, trainer_precision
from locretrieval.training import data as data_module
from locretrieval.training.data import RelevanceBatchSampler, TrainingAugmentation
from locretrieval.training.decoded import decode, decoded_images
from locretrieval.training.relevance import training_pairs


def write_images(folder, count: int = 6, size=(80, 60)) -> list:
    rng = np.random.default_rng(0)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for index in range(count):
        path = folder / f"{index:02d}.{'jpg' if index % 2 else 'png'}"
        Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)).save(path)
        paths.append(path)
    return paths


def test_the_cache_holds_each_image_as_a_step_decodes_it_and_a_changed_image_is_decoded_again(tmp_path):
    paths = write_images(tmp_path / "images")
    cached = decoded_images(paths, (40, 30), tmp_path / "cache", workers=2)
    assert cached.shape == (6, 30, 40, 3) and cached.dtype == np.uint8 and isinstance(cached, np.memmap)
    for path, row in zip(paths, cached):
        np.testing.assert_array_equal(
            row, np.asarray(Image.open(path).convert("RGB").resize((40, 30), Image.Resampling.BILINEAR))
        )
    assert len(list((tmp_path / "cache" / "decoded").glob("*.npy"))) == 1
    assert decoded_images(paths, (40, 30), tmp_path / "cache") is not None  # read back, not decoded again
    assert len(list((tmp_path / "cache" / "decoded").glob("*.npy"))) == 1
    Image.fromarray(np.full((60, 80, 3), 7, dtype=np.uint8)).save(paths[2])  # the image changes (size and time)
    os.utime(paths[2], ns=(1, 1))
    changed = decoded_images(paths, (40, 30), tmp_path / "cache")
    assert (changed[2] == 7).all() and np.array_equal(changed[3], cached[3])
    assert len(list((tmp_path / "cache" / "decoded").glob("*.npy"))) == 2
    other_size = decoded_images(paths, (32, 24), tmp_path / "cache")
    assert other_size.shape == (6, 24, 32, 3)


@pytest.mark.slow
def test_two_processes_decoding_the_same_images_share_one_file(tmp_path, monkeypatch):
    paths = write_images(tmp_path / "images", count=24)
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    # the target lives in a light module: a spawned process imports it, not this test module's torch and Hydra
    jobs = [context.Process(target=decode_into, args=(paths, (40, 30), tmp_path / "cache", results)) for _ in range(2)]
    for job in jobs:
        job.start()
    totals = [results.get(timeout=120) for _ in jobs]
    for job in jobs:
        job.join(60)
        assert job.exitcode == 0
    expected = sum(int(decode(path, (40, 30)).sum()) for path in paths)
    assert totals == [expected, expected]
    files = list((tmp_path / "cache" / "decoded").iterdir())
    assert [f.suffix for f in files if not f.name.endswith(".lock")] == [".npy"]  # no temporary file left


def test_train_py_picks_the_gpu_with_mixed_precision_when_there_is_one(monkeypatch):
    cfg = helpers.compose_config("train")
    assert OmegaConf.select(cfg, "trainer.accelerator") == trainer_accelerator("auto")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert (trainer_accelerator("auto"), trainer_precision("auto")) == ("cpu", "32-true")
    trainer = helpers.compose_config("train").trainer
    assert (trainer.accelerator, trainer.precision) == ("cpu", "32-true")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert (trainer_accelerator("auto"), trainer_precision("auto")) == ("gpu", "16-mixed")
    trainer = helpers.compose_config("train").trainer
    assert (trainer.accelerator, trainer.precision) == ("gpu", "16-mixed")
    assert (trainer_accelerator("cpu"), trainer_precision("cpu")) == (
        "cpu",
        "32-true",
    )  # device=cpu: the CPU even with a GPU
    assert helpers.compose_config("train", "trainer=cpu").trainer.accelerator == "cpu"


def test_the_dataloader_processes_follow_the_cores_when_not_set(monkeypatch):
    for cores, workers in ((1, 1), (2, 1), (16, 8), (64, 8)):
        monkeypatch.setattr(os, "cpu_count", lambda: cores)
        assert data_module.default_workers() == workers


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
