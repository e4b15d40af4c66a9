"""Image pairs selected by frustum overlap (paper Sec. 3.9): the global map's database pairs,
and the query-database pairs of the co-observation ground truth."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from locretrieval.scene import ImageSet

#: Frusta truncated at ``near``/``far`` metres; pairs need a radius >= ``min_radius`` metres;
#: each image keeps at most ``max_per_image`` partners (None: all).
DEFAULT_PAIRS: dict[str, Any] = {"near": 0.1, "far": 50.0, "min_radius": 0.0, "max_per_image": None}


def pair_settings(config: Mapping[str, Any] | None) -> dict[str, Any]:
    """Frustum pair selection options with defaults filled in; unknown keys are an error."""
    settings = {**DEFAULT_PAIRS, **dict(config or {})}
    unknown = sorted(set(settings) - set(DEFAULT_PAIRS))
    if unknown:
        raise ValueError(f"unknown pair selection settings {unknown}; known: {sorted(DEFAULT_PAIRS)}")
    return settings


def overlapping_pairs(first: ImageSet, second: ImageSet, settings: Mapping[str, Any], exclude_self: bool) -> np.ndarray:
    """Pairs ``[P, 2]`` (row of ``first``, row of ``second``) selected by frustum overlap.

    ``settings``: `DEFAULT_PAIRS` keys. Each image of ``first`` keeps the images of ``second`` whose frustum-overlap radius
    (metres; frusta truncated at ``near``/``far``) is positive and at least ``min_radius``,
    at most the ``max_per_image`` largest. ``exclude_self``: both sets are the same, pairs
    (i, i) are left out. Images without a pose are skipped.
    """
    # imported here: the ground-truth package imports localization (co-observations)
    from locretrieval.groundtruth.frustum import TruncatedFrusta, pairwise_overlap_radii

    settings = pair_settings(settings)
    near, far = float(settings["near"]), float(settings["far"])
    rows, columns = np.flatnonzero(first.has_pose), np.flatnonzero(second.has_pose)
    radii = np.zeros((len(first), len(second)))
    radii[np.ix_(rows, columns)] = pairwise_overlap_radii(
        TruncatedFrusta.of_images(first, rows, near, far), TruncatedFrusta.of_images(second, columns, near, far)
    )
    if exclude_self:
        np.fill_diagonal(radii, 0.0)
    keep = (radii > 0) & (radii >= float(settings["min_radius"]))
    if settings["max_per_image"] is not None:
        limit = min(int(settings["max_per_image"]), radii.shape[1])
        order = np.argsort(-radii, axis=1, kind="stable")[:, :limit]
        best = np.zeros_like(keep)
        np.put_along_axis(best, order, True, axis=1)
        keep &= best
    return np.argwhere(keep)


def database_pairs(database: ImageSet, settings: Mapping[str, Any]) -> np.ndarray:
    """Distinct database pairs ``[P, 2]`` (a < b) of the global map, selected by frustum overlap."""
    pairs = overlapping_pairs(database, database, settings, exclude_self=True)
    return np.unique(np.sort(pairs, axis=1), axis=0)
