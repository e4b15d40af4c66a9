"""A scene's global descriptors (`locretrieval.retrieval.descriptors`): cached by the pixels and the model, checked."""

import dataclasses
import logging
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from locretrieval.models import GlobalDescriptor
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.scene import Camera, ImageSet, Scene
from locretrieval.scene.images import read_image


class CenteredThumbnail(GlobalDescriptor):
    """A real, tiny descriptor: an 8x8 grey thumbnail minus the database mean, L2-normalised."""

    learns_from_database = True

    def __init__(self, name: str = "thumbnail", size: int = 8) -> None:
        super().__init__(name)
        self.size = size
        self.mean: np.ndarray | None = None
        self.describe_calls = 0
        self.fit_calls = 0

    def _thumbnails(self, images: ImageSet) -> np.ndarray:
        rows = [
            np.asarray(Image.fromarray(read_image(path, grayscale=True)).resize((self.size, self.size)), np.float32)
            for path in images.paths
        ]
        return np.stack(rows).reshape(len(images), -1) / 255.0

    def fit(self, database: ImageSet) -> None:
        self.fit_calls += 1
        self.mean = self._thumbnails(database).mean(axis=0)

    def describe(self, images: ImageSet) -> np.ndarray:
        self.describe_calls += 1
        centred = self._thumbnails(images) - self.mean
        return (centred / np.linalg.norm(centred, axis=1, keepdims=True)).astype(np.float32)

    def identity(self) -> dict:
        return {"model": "thumbnail", "size": self.size}


def write_images(root: Path, names: list[str], seed: int) -> ImageSet:
    rng = np.random.default_rng(seed)
    for name in names:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.integers(0, 256, (24, 32), dtype=np.uint8)).save(root / name)
    camera = Camera("PINHOLE", 32, 24, (30.0, 30.0, 16.0, 12.0))
    count = len(names)
    return ImageSet(names, root, [camera] * count, np.tile([1.0, 0, 0, 0], (count, 1)), rng.normal(size=(count, 3)))


@pytest.fixture
def scene(tmp_path) -> Scene:
    database = write_images(tmp_path / "images", [f"db/{i}.png" for i in range(6)], seed=0)
    queries = write_images(tmp_path / "images", [f"query/{i}.png" for i in range(3)], seed=1)
    return Scene("tiny", database, queries)


def test_describe_scene_caches_only_descriptors(tmp_path, scene, caplog):
    model = CenteredThumbnail()
    with caplog.at_level(logging.INFO):
        database, queries = describe_scene(model, scene, tmp_path / "cache")
    assert "cache miss" in caplog.text
    assert (model.fit_calls, model.describe_calls) == (1, 2)
    assert database.shape == (6, 64) and queries.shape == (3, 64)
    cached = list((tmp_path / "cache" / "descriptors").glob("*.npz"))
    assert len(cached) == 1
    with np.load(cached[0]) as stored:
        assert sorted(stored.files) == ["database", "queries"]  # no fitted state: one copy per query set

    fresh = CenteredThumbnail()
    caplog.clear()
    with caplog.at_level(logging.INFO):
        cached_database, cached_queries = describe_scene(fresh, scene, tmp_path / "cache")
    assert "cache hit" in caplog.text
    assert (fresh.fit_calls, fresh.describe_calls) == (0, 0)
    np.testing.assert_array_equal(cached_database, database)
    np.testing.assert_array_equal(cached_queries, queries)
    assert fresh.mean is None  # a cache hit leaves the model unfitted


def test_changed_model_config_misses_the_cache(tmp_path, scene):
    describe_scene(CenteredThumbnail(size=8), scene, tmp_path)
    other = CenteredThumbnail(size=4)
    database, _ = describe_scene(other, scene, tmp_path)
    assert other.describe_calls == 2 and database.shape == (6, 16)
    assert len(list((tmp_path / "descriptors").glob("*.npz"))) == 2


def test_descriptor_cache_follows_the_pixels_not_the_poses(tmp_path, scene):
    describe_scene(CenteredThumbnail(), scene, tmp_path)
    database = scene.database
    moved = dataclasses.replace(database, tvec=database.tvec + 1.0)
    model = CenteredThumbnail()
    describe_scene(model, Scene("tiny", moved, scene.queries), tmp_path)
    assert model.describe_calls == 0  # new poses, same images: cache hit
    Image.fromarray(np.zeros((24, 32), dtype=np.uint8)).save(database.paths[0])  # same size, new content
    os.utime(database.paths[0], ns=(1, 1))
    describe_scene(model, scene, tmp_path)
    assert model.describe_calls == 2


def test_describe_scene_without_cache_dir(scene):
    model = CenteredThumbnail()
    describe_scene(model, scene, None)
    describe_scene(model, scene, None)
    assert model.describe_calls == 4


class Unnormalised(CenteredThumbnail):
    def describe(self, images: ImageSet) -> np.ndarray:
        descriptors = super().describe(images)
        descriptors[1] *= 2.0
        return descriptors


class Float64(CenteredThumbnail):
    def describe(self, images: ImageSet) -> np.ndarray:
        return super().describe(images).astype(np.float64)


class WrongCount(CenteredThumbnail):
    def describe(self, images: ImageSet) -> np.ndarray:
        return super().describe(images)[:-1]


class NonFinite(CenteredThumbnail):
    def describe(self, images: ImageSet) -> np.ndarray:
        descriptors = super().describe(images)
        descriptors[2, 0] = np.inf
        return descriptors


@pytest.mark.parametrize(
    ("model_class", "message"),
    [
        (Unnormalised, r"'db/1.png' has L2 norm 2\.0"),
        (Float64, "float64 descriptors; expected float32"),
        (WrongCount, r"\(5, 64\) descriptors for 6 images"),
        (NonFinite, "'db/2.png' has non-finite values"),
    ],
)
def test_invalid_descriptors_are_rejected_naming_model_and_image(scene, tmp_path, model_class, message):
    with pytest.raises(ValueError, match=message) as error:
        describe_scene(model_class(name="broken"), scene, tmp_path)
    assert "'broken'" in str(error.value)
    assert not list(tmp_path.glob("descriptors/*.npz"))
