"""Fixtures of the training tests."""

import helpers
import pytest
from training_runs import SCENE

from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("training_scene")
    render_synthetic_dataset(helpers.render_settings(SCENE), root)
    return load_kapture_scene("tiny", [root / "mapping"], [root / "query"], frustum_far=25.0)
