"""The config resolvers: multirun job folders that always fit."""

import os

import helpers
from omegaconf import OmegaConf

from locretrieval.config import JOB_DIRNAME_LENGTH, job_dirname

#: 15 long overrides, as a sweep over the training's nested keys writes them.
LONG = [f"callbacks.localization_validation.some_rather_long_option_{i}=value_number_{i}" for i in range(15)]


def test_job_folders_of_15_long_overrides_are_short_unique_and_readable():
    names = [job_dirname(job, ",".join([f"loss=ap_{job}", *LONG])) for job in range(3)]
    assert all(len(name) == JOB_DIRNAME_LENGTH for name in names) and len(set(names)) == 3
    assert names[0].startswith("0_loss=ap_0,some_rather_long_option_0=value_number_0,")  # keys shortened
    # the hash is of the whole label: jobs whose start agrees differ by it
    assert len({name.rsplit("-", 1)[1] for name in names}) == 3
    assert len(os.fsencode(names[0])) < 255  # the file system's limit of a name


def test_short_labels_stay_as_they_are_and_nothing_can_leave_the_sweep_folder():
    assert job_dirname(2, "synthetic_mall_densevlad") == "2_synthetic_mall_densevlad"
    assert job_dirname(0, "loss=ap,sampler.anchors=3") == "0_loss=ap,anchors=3"
    assert "/" not in job_dirname(1, "model.name=../../outside") and job_dirname(1, "x/..") != "1_x/.."


def test_both_entry_points_name_their_jobs_by_the_resolver():
    for name in ("train", "evaluate"):
        subdir = OmegaConf.load(helpers.CONFIGS / f"{name}.yaml").hydra.sweep._get_node("subdir")._value()
        assert subdir.startswith("${job_dirname:${hydra.job.num},"), name
