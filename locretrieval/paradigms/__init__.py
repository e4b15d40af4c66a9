"""Localization paradigms (paper Sec. 3.1-3.3): `approximation` (paradigm 1), `local_sfm` (2a) and
`global_sfm` (2b), each a `base.Paradigm` subclass built from its ``configs/paradigms/<name>.yaml``
by ``_target_``; the SfM ones run on the pipeline of `locretrieval.sfm`. `locretrieval.benchmark`
runs the enabled ones (`base.Paradigms`). Import the modules you need: this package imports
nothing on its own, so that reading a paradigm's settings does not load pycolmap.
"""
