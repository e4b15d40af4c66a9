"""Localization paradigms. Each maps ``(scene, rankings, config, cache_dir)`` to `PoseEstimates`.

``PARADIGMS`` (paradigm name, a section of configs/paradigms/*.yaml -> entry point) is built on
first use, so that code needing only `PoseEstimates` (metrics, report) does not import pycolmap.
"""

import importlib

from locretrieval.localization.estimates import PoseEstimates

PARADIGM_MODULES = ("approximation", "local_sfm", "global_sfm")

__all__ = ["PARADIGMS", "PoseEstimates"]


def __getattr__(name: str):
    if name == "PARADIGMS":
        return {p: importlib.import_module(f"locretrieval.localization.{p}").run for p in PARADIGM_MODULES}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
