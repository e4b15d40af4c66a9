"""The paradigms' sections of the config (`locretrieval.paradigms.base`), checked."""

import pytest
from helpers import evaluate_config
from omegaconf import OmegaConf

from locretrieval.config import ConfigError, validated
from locretrieval.paradigms.base import Paradigms


def test_paradigm_sections_are_checked():
    paradigms = evaluate_config("paths.root_dir=/nonexistent").paradigms  # configs/paradigms/default.yaml, composed
    OmegaConf.set_struct(paradigms, False)
    assert validated(Paradigms, paradigms, "paradigms").enabled() == [
        "approximation",
        "local_sfm",
        "global_sfm",
    ]
    paradigms.local_sfm.enabled = False
    assert validated(Paradigms, paradigms, "paradigms").enabled() == ["approximation", "global_sfm"]
    paradigms.globl_sfm = {"enabled": True}
    with pytest.raises(
        ConfigError,
        match=r"paradigms.globl_sfm: a paradigm section without _target_ .*"
        r"the sections are \['approximation', 'local_sfm', 'global_sfm', 'globl_sfm'\]",
    ):
        validated(Paradigms, paradigms, "paradigms")
    with pytest.raises(ConfigError, match=r"^paradigms: one paradigm's YAML in place of the group"):
        validated(Paradigms, evaluate_config("paradigms=local_sfm").paradigms, "paradigms")
