"""Image pairs selected by frustum overlap (paper Sec. 3.9): the global map's database pairs,
and the query-database pairs of the co-observation ground truth."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from locretrieval.scene import ImageSet

#: Frusta truncated at ``near``/``far`` metres; a pair needs a radius above ``min_radius``
#: metres (as a relevant pair of the frustum ground truth); each image keeps at most
#: ``max_per_image`` partners (None: all).
DEFAULT_PAIRS: dict[str, Any] = {"near": 0.1, "far": 50.0, "min_radius": 0.0, "max_per_image": None}
#: Image pairs whose overlap radii are held in memory at once (a block of rows of the first set).
PAIRS_PER_CHUNK = 1 << 20


def pair_settings(config: Mapping[str, Any] | None) -> dict[str, Any]:
    """Frustum pair selection options with defaults filled in; unknown keys or bad values are an error."""
    settings = {**DEFAULT_PAIRS, **dict(config or {})}
    unknown = sorted(set(settings) - set(DEFAULT_PAIRS))
    if unknown:
        raise ValueError(f"unknown pair selection settings {unknown}; known: {sorted(DEFAULT_PAIRS)}")
    if float(settings["min_radius"]) < 0:
        raise ValueError(f"pair selection min_radius must be >= 0 metres, got {settings['min_radius']}")
    if settings["max_per_image"] is not None and int(settings["max_per_image"]) < 1:
        raise ValueError(f"pair selection max_per_image must be >= 1 or None, got {settings['max_per_image']}")
    return settings


def overlapping_pairs(first: ImageSet, second: ImageSet, settings: Mapping[str, Any], exclude_self: bool) -> np.ndarray:
    """Pairs ``[P, 2]`` (row of ``first``, row of ``second``) selected by frustum overlap, sorted.

    ``settings``: `DEFAULT_PAIRS` keys. Each image of ``first`` keeps the images of ``second``
    whose frustum-overlap radius (metres; frusta truncated at ``near``/``far``) exceeds
    ``min_radius``, at most the ``max_per_image`` largest (ties: lower row of ``second``
    first). ``exclude_self``: both sets are the same, pairs (i, i) are left out. Images
    without a pose are skipped. Radii are computed for `PAIRS_PER_CHUNK` pairs at a time.
    """
    # imported here: the ground-truth package imports localization (co-observations)
    from locretrieval.groundtruth.frustum import TruncatedFrusta, pairwise_overlap_radii

    settings = pair_settings(settings)
    near, far = float(settings["near"]), float(settings["far"])
    rows, columns = np.flatnonzero(first.has_pose), np.flatnonzero(second.has_pose)
    second_frusta = TruncatedFrusta.of_images(second, columns, near, far)
    rows_per_chunk = max(1, PAIRS_PER_CHUNK // max(1, len(columns)))
    pairs = [np.empty((0, 2), dtype=np.int64)]
    for start in range(0, len(rows), rows_per_chunk):
        chunk = rows[start : start + rows_per_chunk]
        radii = pairwise_overlap_radii(TruncatedFrusta.of_images(first, chunk, near, far), second_frusta)
        if exclude_self:
            radii[chunk[:, None] == columns[None]] = 0.0
        chunk_rows, chunk_columns = np.nonzero(_selected(radii, float(settings["min_radius"]), settings["max_per_image"]))
        pairs.append(np.column_stack([chunk[chunk_rows], columns[chunk_columns]]))
    return np.concatenate(pairs)


def _selected(radii: np.ndarray, min_radius: float, max_per_image: int | None) -> np.ndarray:
    """Boolean ``[Q, N]``: radii above ``min_radius``, at most the ``max_per_image`` largest of
    each row (ties: lower column first)."""
    keep = radii > min_radius
    if max_per_image is None or int(max_per_image) >= radii.shape[1]:
        return keep
    limit = int(max_per_image)
    kth_largest = -np.partition(-radii, limit - 1, axis=1)[:, limit - 1 : limit]
    above = radii > kth_largest
    ties = radii == kth_largest
    room = limit - above.sum(axis=1, keepdims=True)
    return keep & (above | (ties & (np.cumsum(ties, axis=1) <= room)))


def database_pairs(database: ImageSet, settings: Mapping[str, Any]) -> np.ndarray:
    """Distinct database pairs ``[P, 2]`` (a < b) of the global map, selected by frustum overlap."""
    pairs = overlapping_pairs(database, database, settings, exclude_self=True)
    return np.unique(np.sort(pairs, axis=1), axis=0)
