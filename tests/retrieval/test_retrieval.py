import dataclasses
import logging
import os
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from locretrieval.models import GlobalDescriptor
from locretrieval.retrieval import EMPTY, random_ranking, top_k
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.retrieval.index import search
from locretrieval.scene import Camera, ImageSet, Scene
from locretrieval.scene.images import read_image


def unit_rows(rng: np.random.Generator, rows: int, dim: int) -> np.ndarray:
    values = rng.normal(size=(rows, dim)).astype(np.float32)
    return values / np.linalg.norm(values, axis=1, keepdims=True)


def brute_force(queries: np.ndarray, database: np.ndarray, depth: int) -> tuple[np.ndarray, np.ndarray]:
    scores = queries.astype(np.float64) @ database.astype(np.float64).T
    order = np.argsort(-scores, axis=1, kind="stable")[:, :depth]
    return order, np.take_along_axis(scores, order, axis=1)


def ranked(depth: int = 5, chunk_size: int = 256) -> dict:
    """`search`'s depth, ranking name and chunk size of these tests."""
    return {"depth": depth, "name": "test", "chunk_size": chunk_size}


@pytest.mark.parametrize("chunk_size", [7, 37, 1000])
def test_search_equals_brute_force(chunk_size):
    rng = np.random.default_rng(0)
    queries, database = unit_rows(rng, 37, 16), unit_rows(rng, 120, 16)
    ranking = search(queries, database, depth=20, name="random", chunk_size=chunk_size)
    indices, scores = brute_force(queries, database, 20)
    np.testing.assert_array_equal(ranking.indices, indices)
    np.testing.assert_allclose(ranking.scores, scores, atol=1e-5)
    assert ranking.kind == "descriptor" and ranking.name == "random"
    np.testing.assert_array_equal(ranking.query_descriptors, queries)
    np.testing.assert_array_equal(ranking.database_descriptors, database)


def test_search_orders_ties_by_database_index():
    database = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0], [1.0, 0.0]], dtype=np.float32)
    ranking = search(np.array([[1.0, 0.0]], dtype=np.float32), database, **ranked(depth=4))
    np.testing.assert_array_equal(ranking.indices, [[0, 2, 3, 1]])


@pytest.mark.parametrize("chunk_size", [5, 64])
def test_exclude_self_drops_exactly_the_own_index(chunk_size):
    rng = np.random.default_rng(1)
    descriptors = unit_rows(rng, 30, 8)
    descriptors[10] = descriptors[3]  # a duplicate: both tie at score 1 with each other
    ranking = search(descriptors, descriptors, **ranked(depth=6, chunk_size=chunk_size), exclude_self=True)
    assert ranking.indices.shape == (30, 6)
    assert not (ranking.indices == np.arange(30)[:, None]).any()
    scores = descriptors.astype(np.float64) @ descriptors.astype(np.float64).T
    np.fill_diagonal(scores, -np.inf)
    expected_scores = -np.sort(-scores, axis=1)[:, :6]
    np.testing.assert_allclose(ranking.scores, expected_scores, atol=1e-5)
    # Each slot holds the image its score belongs to (the duplicate may tie at the last slot).
    np.testing.assert_allclose(np.take_along_axis(scores, ranking.indices, axis=1), ranking.scores, atol=1e-5)
    assert ranking.indices[3, 0] == 10 and ranking.indices[10, 0] == 3
    np.testing.assert_allclose(ranking.scores[[3, 10], 0], 1.0, atol=1e-6)


def test_exclude_self_when_duplicates_crowd_out_the_own_index():
    # Five identical rows: faiss may return the others before row i; i must still be dropped.
    descriptors = np.tile(np.array([[0.6, 0.8]], dtype=np.float32), (5, 1))
    ranking = search(descriptors, descriptors, **ranked(depth=2), exclude_self=True)
    assert ranking.indices.shape == (5, 2)
    assert not (ranking.indices == np.arange(5)[:, None]).any()
    assert all(len(set(row)) == 2 for row in ranking.indices.tolist())


def test_depth_is_clamped_with_a_warning(caplog):
    rng = np.random.default_rng(2)
    database = unit_rows(rng, 5, 4)
    with caplog.at_level(logging.WARNING):
        ranking = search(unit_rows(rng, 3, 4), database, **ranked(depth=50))
    assert ranking.indices.shape == (3, 5)
    assert (ranking.indices >= 0).all()
    assert np.array_equal(np.sort(ranking.indices, axis=1), np.tile(np.arange(5), (3, 1)))
    assert "clamped to 5" in caplog.text
    assert search(database, database, **ranked(depth=50), exclude_self=True).indices.shape == (5, 4)


def test_search_errors_name_the_problem():
    rng = np.random.default_rng(3)
    database = unit_rows(rng, 6, 4)
    with pytest.raises(ValueError, match=r"queries \[2, 3\] vs database \[6, 4\]"):
        search(unit_rows(rng, 2, 3), database, **ranked())
    bad = database.copy()
    bad[4, 1] = np.nan
    with pytest.raises(ValueError, match="database descriptors: row 4"):
        search(database, bad, **ranked())
    with pytest.raises(ValueError, match="query descriptors: row 4"):
        search(bad, database, **ranked())
    with pytest.raises(ValueError, match="empty database"):
        search(database, np.zeros((0, 4), dtype=np.float32), **ranked())
    with pytest.raises(ValueError, match="depth must be >= 1"):
        search(database, database, **ranked(depth=0))
    with pytest.raises(ValueError, match="exclude_self"):
        search(database[:3], database, **ranked(), exclude_self=True)


# -- describe_scene and its cache ---------------------------------------------------------


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


def test_random_ranking_is_seeded_without_repeats_and_clamped():
    first, again, other = (random_ranking(20, 30, 10, seed) for seed in (0, 0, 1))
    assert first.kind == "baseline" and first.indices.shape == (20, 10)
    assert all(len(set(row)) == 10 for row in first.indices) and first.indices.max() < 30
    np.testing.assert_array_equal(first.indices, again.indices)
    assert (first.indices != other.indices).any()
    assert random_ranking(3, 4, 10, 0).depth == 4


@pytest.mark.parametrize("kind", ["continuous", "integer", "rounded_with_nan", "few_rankable"])
def test_top_k_takes_the_best_entries_ties_by_lower_index_also_when_a_tie_straddles_the_depth(kind):
    rng = np.random.default_rng(7)
    scores = {
        "continuous": rng.random((40, 300)),
        "integer": rng.integers(0, 4, (40, 300)).astype(float),  # ties at every depth
        "rounded_with_nan": np.where(rng.random((40, 300)) < 0.3, np.nan, np.round(rng.normal(size=(40, 300)), 1)),
        "few_rankable": rng.random((40, 300)),  # fewer rankable entries than the depth: EMPTY slots
    }[kind]
    valid = rng.random(scores.shape) < (0.05 if kind == "few_rankable" else 0.8)
    for depth in (1, 7, 50, 300):  # the partial selection below N / 4, the full sort above
        indices, top = top_k(scores, depth, valid)
        for row in range(len(scores)):
            ranked = sorted(
                (-scores[row, n], n) for n in range(scores.shape[1]) if valid[row, n] and np.isfinite(scores[row, n])
            )
            expected = [n for _, n in ranked[:depth]]
            assert indices[row].tolist() == expected + [EMPTY] * (depth - len(expected))
            np.testing.assert_array_equal(top[row, : len(expected)], scores[row, expected].astype(np.float32))
            assert (top[row, len(expected) :] == 0).all()
