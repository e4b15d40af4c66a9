"""The training data pipeline: images decoded once into a shared memory-mapped cache, the device
train.py picks, the DataLoader's processes."""

import multiprocessing
import os

import helpers
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

from locretrieval.config import trainer_accelerator, trainer_precision
from locretrieval.training import data as data_module
from locretrieval.training.decoded import decode, decoded_images


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


def _decode_into(paths, cache, results) -> None:
    results.put(np.asarray(decoded_images(paths, (40, 30), cache, workers=1)).sum())


@pytest.mark.slow
def test_two_processes_decoding_the_same_images_share_one_file(tmp_path, monkeypatch):
    paths = write_images(tmp_path / "images", count=24)
    context = multiprocessing.get_context("spawn")
    results = context.Queue()
    jobs = [context.Process(target=_decode_into, args=(paths, tmp_path / "cache", results)) for _ in range(2)]
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
