"""The objective train.py returns to a sweep (`locretrieval.training.objective`): the metric at its best or
last validation, refused before any work when validation never logs it."""

from pathlib import Path

import pytest
from omegaconf import OmegaConf
from training_runs import METRIC, validation_table

from locretrieval.build import benchmark_settings
from locretrieval.config import ConfigError
from locretrieval.training.objective import Objective


def test_the_objective_is_the_metric_at_its_best_or_last_validation_after_training():
    table = validation_table(
        [(-1, METRIC, 90.0), (0, METRIC, 20.0), (1, METRIC, 40.0), (2, METRIC, 30.0), (1, "val/other", 99.0)]
    )
    assert Objective(METRIC, "best").value(table) == (1, 40.0)  # before training (90) does not count
    assert Objective(METRIC, "last").value(table) == (2, 30.0)
    sfm = "val/global_sfm/pnp/k5/0.25m_2deg"  # logged every sfm_every_n_epochs: its last validation is the last
    assert Objective(sfm, "last").value(validation_table([(-1, sfm, 5.0), (1, sfm, 7.0), (2, METRIC, 1.0)])) == (1, 7.0)
    with pytest.raises(ValueError, match=r"optimized_metric: 'val/missing' was not logged .* val/approximation/ewb/k3"):
        Objective("val/missing", "best").value(table)
    for bad in (float("nan"), float("-inf")):
        broken = validation_table([(0, METRIC, 20.0), (1, METRIC, bad)])
        with pytest.raises(ValueError, match=rf"optimized_metric: '{METRIC}' is {bad} .* epoch 1, not a finite"):
            Objective(METRIC, "best").value(broken)
    with pytest.raises(ConfigError, match=r"optimized_validation: 'first'; expected one of \['best', 'last'\]"):
        Objective.from_config(OmegaConf.create({"optimized_metric": METRIC, "optimized_validation": "first"}))


def test_an_objective_that_validation_never_logs_is_refused_before_the_scene_is_prepared(tmp_path):
    from helpers import train
    from training_runs import train_config

    sfm = "val/global_sfm/pnp/k5/0.25m_2deg"  # the test config validates without the SfM paradigms
    for metric in ("val/approximation/ewb/k4/5m_10deg", sfm):
        cfg = train_config(tmp_path, f"optimized_metric={metric}")
        with pytest.raises(
            ConfigError, match=rf"optimized_metric: '{metric}' is not logged by validation; .* {METRIC}"
        ):
            train(cfg, tmp_path / "run")
        assert not (Path(cfg.paths.cache_dir) / "synthetic").exists()
    cfg = train_config(tmp_path, f"optimized_metric={sfm}", "callbacks.localization_validation.sfm_every_n_epochs=1")
    from locretrieval.training.callbacks import validation_metrics  # accepted once the SfM paradigms are validated

    assert sfm in validation_metrics(benchmark_settings(cfg), ["relative_pose"], with_sfm=True)
