"""Training on one's own place: ``train.py data=colmap`` (the scene ``data=photos`` reads too) with
co-observation relevance from the model's tracks, and such a scene listed beside another in
``training.scenes``."""

from __future__ import annotations

from types import SimpleNamespace

import helpers
import numpy as np
import pytest
from helpers import train
from hydra.utils import instantiate
from own_place import render_walk, write_model
from training_runs import TINY_TRAINING

from locretrieval.build import build_training
from locretrieval.cli import composed_training_scenes


def place(root, seed: int, count: int):
    """A walk of ``count`` photos and its COLMAP model, 3D points on the shops across it; returns
    ``(model folder, photo folder, image names, [images, points] membership of the tracks)``."""
    walk = render_walk(root / "photos", count, 96, 72, gps=False, seed=seed)
    rng = np.random.default_rng(seed)
    points = np.column_stack([rng.uniform(0.0, 20.0, 200), rng.uniform(3.0, 5.0, 200), rng.uniform(0.0, 4.0, 200)])
    tracks = [list(rng.choice(count, size=rng.integers(2, 5), replace=False)) for _ in points]
    write_model(root / "sparse", walk.names, walk.camera, walk.qvec, walk.tvec, tracks, points)
    membership = np.zeros((count, len(tracks)), dtype=int)
    for point, track in enumerate(tracks):
        membership[track, point] = 1
    return root / "sparse", walk.folder, walk.names, membership


@pytest.fixture(scope="module")
def places(tmp_path_factory):
    root = tmp_path_factory.mktemp("own_place_training")
    return root, place(root / "a", 0, 15), place(root / "b", 1, 10)


def test_train_py_trains_on_a_colmap_scene_beside_another_with_relevance_from_its_tracks(tmp_path, places):
    root, (model, images, names, membership), (other_model, other_images, other_names, other_membership) = places
    listed = f"{{config: colmap, name: other, model: {other_model}, images: {other_images}, metres_per_unit: 1.0}}"
    cfg = helpers.compose_config(
        "train", f"paths.root_dir={tmp_path}", f"output_dir={tmp_path}/run", "device=cpu", "data=colmap",
        f"data.model={model}", f"data.images={images}", "data.metres_per_unit=1.0", "model.max_side=96",
        *TINY_TRAINING, "datamodule.image_size=[96,72]", "trainer.max_epochs=1", "trainer.enable_progress_bar=false",
        "+trainer.fast_dev_run=true", "train_relevance=co_observation", "train_relevance.definition.min_shared=1",
        f"training.scenes=[{listed}]", "sampler.anchors=4",
    )  # fmt: skip
    scene = instantiate(cfg.data)
    run = build_training(cfg, composed_training_scenes(cfg))  # what train.py builds
    parts = SimpleNamespace(
        sets=[world.database for world in run.worlds], pairs=run.datamodule.pairs, sampler=run.datamodule.sampler
    )
    other_database = [name for index, name in enumerate(other_names) if index % 5]  # a listed scene's database
    assert [s.names for s in parts.sets] == [scene.database.names, other_database]
    graded = parts.pairs.graded.toarray()
    for offset, (images, rows_of, tracks) in enumerate(
        [(parts.sets[0], names, membership), (parts.sets[1], other_names, other_membership)]
    ):
        start = sum(len(s) for s in parts.sets[:offset])
        block = graded[start : start + len(images), start : start + len(images)]
        rows = tracks[[rows_of.index(name) for name in images.names]]
        shared = rows @ rows.T  # the tracks' co-observations, counted by hand
        expected = np.where(shared >= 1, shared / np.maximum(np.diag(shared), 1)[:, None], 0.0)
        np.fill_diagonal(expected, 0.0)
        np.testing.assert_allclose(block, expected)
    assert not graded[: len(parts.sets[0]), len(parts.sets[0]) :].any()  # never related across scenes
    assert not (tmp_path / ".cache" / "features").exists()  # no SfM of ours: the tracks are the model's
    validator = train(cfg, tmp_path / "run")  # a training step, then validation on the model's queries
    assert validator.scene.queries.names == scene.queries.names and validator.history
