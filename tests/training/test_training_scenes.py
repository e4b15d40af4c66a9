"""Training on several scenes at once: published datasets' miniatures and a kapture folder of
images, relevance within each scene, batches drawn across them, validation on another scene."""

from pathlib import Path
from types import SimpleNamespace

import helpers
import numpy as np
import pytest
from helpers import train
from hydra.utils import instantiate
from published_layouts import LAYOUTS, SCENE, install, write_kapture_folder
from training_runs import train_config

from locretrieval.build import build_training
from locretrieval.cli import composed_training_scenes
from locretrieval.config import ConfigError
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset
from locretrieval.sfm.features import extract_features


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    """Aachen's and Baidu's downloader layouts and a plain kapture folder of JPEG images, from a rendered scene."""
    root = tmp_path_factory.mktemp("training_scenes")
    render_synthetic_dataset(helpers.render_settings({**SCENE, "seed": 9}), root / "source")
    scene = load_kapture_scene("source", [root / "source" / "mapping"], [root / "source" / "query"])
    local = {
        **extract_features(scene.database, helpers.sfm_settings().features, root / "cache", 1).load(
            scene.database.names
        ),
        **extract_features(scene.queries, helpers.sfm_settings().features, root / "cache", 1).load(scene.queries.names),
    }
    for name in ("aachen", "baidu"):
        install(LAYOUTS[name], (scene, local), root / "data")
    write_kapture_folder(
        root / "data" / "photos" / "mapping", scene.database, np.arange(8), "street/{i:03d}.jpg", posed=True
    )
    write_kapture_folder(
        root / "data" / "photos" / "query", scene.queries, np.arange(2), "phone/{i:03d}.jpg", posed=True
    )
    return root / "data"


SCENES = "training.scenes=[aachen,baidu,{config:kapture,mapping:photos/mapping,queries:[photos/query]}]"


@pytest.mark.slow
def test_several_scenes_are_trained_on_and_never_related_across(tmp_path, data_dir):
    cfg = train_config(
        tmp_path, f"paths.data_dir={data_dir}", SCENES, "sampler.anchors=6", "+trainer.fast_dev_run=true"
    )
    scene = instantiate(cfg.data)
    run = build_training(cfg, composed_training_scenes(cfg))  # what train.py builds
    parts = SimpleNamespace(
        sets=[world.database for world in run.worlds], pairs=run.datamodule.pairs, sampler=run.datamodule.sampler
    )
    sizes = [len(images) for images in parts.sets]
    assert sizes == [len(scene.database), 12, 12, 8]  # the validation scene's database, Aachen's, Baidu's, the photos'
    assert parts.sets[1].names[0].startswith("db/") and parts.sets[3].names[0].startswith("street/")
    starts = np.cumsum([0, *sizes])
    scene_of = np.repeat(np.arange(len(sizes)), sizes)
    graded, related = parts.pairs.graded.toarray(), parts.pairs.related.toarray()
    across = scene_of[:, None] != scene_of[None]
    assert not graded[across].any() and not related[across].any()  # relevance within each scene, never across
    for index in range(1, 4):  # each listed scene has relevant pairs of its own
        block = slice(starts[index], starts[index + 1])
        assert graded[block, block].any()
    drawn = [scene_of[batch] for batch in parts.sampler]
    assert any(len(set(batch)) > 1 for batch in drawn)  # batches drawn across scenes
    for batch in parts.sampler:
        relevance, _ = parts.pairs.batch(np.array(batch))
        assert not relevance[scene_of[batch][:, None] != scene_of[batch][None]].any()
    validator = train(cfg, tmp_path / "run")  # a training step, then validation on the synthetic scene's queries
    assert validator.scene.queries.names == scene.queries.names and validator.history


def test_a_listed_scene_that_is_no_data_config_is_named_before_any_work(tmp_path):
    cfg = train_config(tmp_path, "training.scenes=[aachen,atlantis]")
    with pytest.raises(ConfigError, match=r"training.scenes: no data config 'atlantis'; expected one of \[.*'baidu'"):
        train(cfg, tmp_path / "run")
    assert not (Path(cfg.paths.cache_dir) / "synthetic").exists()  # the validation scene was not rendered
