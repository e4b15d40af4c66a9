"""The run behind export.py (`locretrieval.export.run`): its settings checked before any work, its run folder."""

import helpers
import pytest
from helpers import HOSTILE_MODEL, compose_config, export
from hydra import compose, initialize_config_dir

from locretrieval.config import ConfigError


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["export=[pairs,maps]"], r"export: lists what to write, some of \['pairs', 'descriptors', 'onnx'\]"),
        (["pairs.k=51"], r"pairs.k: 51 is more than retrieval.depth=50"),
        (["pairs.formats=[colmap]"], r"pairs.formats: unknown \['colmap'\]"),
        (["descriptors.formats=[npy]"], r"descriptors.formats: unknown \['npy'\]"),
        (["export=[onnx]", "onnx.opset=9"], r"onnx.opset: must be between 14 and 20"),
    ],
)
def test_export_checks_its_settings_before_any_work(tmp_path, overrides, message):
    with pytest.raises(ConfigError, match=message):
        export(compose_config("export", f"paths.root_dir={tmp_path}", *overrides), tmp_path / "out")
    assert not any(tmp_path.iterdir())  # nothing rendered, described or written


def test_the_export_run_folder_keeps_names_inside_outputs():
    with initialize_config_dir(config_dir=str(helpers.CONFIGS), version_base="1.3"):
        config = compose("export", overrides=[f"model.name='{HOSTILE_MODEL}'"], return_hydra_config=True)
    run_dir = config.hydra.run.dir
    assert run_dir.startswith("outputs/export/synthetic_mall/") and ".." not in run_dir.split("/")
    assert run_dir.count("/") == 4  # outputs/export/<dataset>/<model>/<date>
