"""Localization paradigms (paper Sec. 3.1-3.3) and what they are built from.

Each paradigm module (`approximation`, `local_sfm`, `global_sfm`) has a settings schema and
a ``run(scene, rankings, settings, sfm, cache_dir) -> list[PoseEstimates]`` entry point;
`locretrieval.benchmark` calls them. Import the modules you need: this package imports
nothing on its own, so that reading `PoseEstimates` does not load pycolmap.
"""
