"""Localization paradigms. Each maps ``(scene, rankings, config, cache_dir)`` to `PoseEstimates`."""

from locretrieval.localization import approximation, global_sfm, local_sfm
from locretrieval.localization.estimates import PoseEstimates

#: Paradigm name (a section of configs/paradigms/*.yaml) -> entry point.
PARADIGMS = {
    "approximation": approximation.run,
    "local_sfm": local_sfm.run,
    "global_sfm": global_sfm.run,
}

__all__ = ["PARADIGMS", "PoseEstimates"]
