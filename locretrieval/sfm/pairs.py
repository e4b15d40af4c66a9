"""Image pairs selected by frustum overlap (paper Sec. 3.9): the global map's database pairs,
and the query-database pairs of the co-observation ground truth."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from locretrieval.config import require
from locretrieval.scene import ImageSet, Scene

#: Image pairs whose overlap radii are held in memory at once (a block of rows of the first set).
PAIRS_PER_CHUNK = 1 << 20


@dataclass
class PairSelection:
    """Image pairs by frustum overlap: frusta truncated at ``near``/``far`` metres (``far``
    ``None``: the scene's `Scene.frustum_far`); a pair needs an overlap radius above
    ``min_radius`` metres; each image keeps at most its ``max_per_image`` most overlapping
    partners (``None``: all)."""

    near: float
    far: float | None
    min_radius: float
    max_per_image: int | None

    def __post_init__(self) -> None:
        require(self.near > 0, "near", f"must be a positive depth in metres, got {self.near}")
        require(self.far is None or self.far > self.near, "far", f"must exceed near ({self.near} m), got {self.far}")
        require(self.min_radius >= 0, "min_radius", f"must be >= 0 metres, got {self.min_radius}")
        require(
            self.max_per_image is None or self.max_per_image >= 1,
            "max_per_image",
            f"must be >= 1 or null (all), got {self.max_per_image}",
        )

    def for_scene(self, scene: Scene) -> "PairSelection":
        """This selection with ``far`` set to the scene's frustum far plane where it is ``None``."""
        return replace(self, far=scene.far_plane(self.far, "sfm.map_pairs.far"))


def overlapping_pairs(first: ImageSet, second: ImageSet, selection: PairSelection, exclude_self: bool) -> np.ndarray:
    """Pairs ``[P, 2]`` (row of ``first``, row of ``second``) selected by frustum overlap, sorted.

    Each image of ``first`` keeps the images of ``second`` whose frustum-overlap radius exceeds
    ``selection.min_radius``, at most the ``max_per_image`` largest (ties: lower row of
    ``second`` first). ``exclude_self``: both sets are the same, pairs (i, i) are left out.
    Images without a pose are skipped. Radii are computed for `PAIRS_PER_CHUNK` pairs at a time.
    """
    from locretrieval.frusta import TruncatedFrusta, pairwise_overlap_radii  # here: scipy's linprog, not in workers

    if selection.far is None:
        raise ValueError("pair selection: far is unset; resolve it with PairSelection.for_scene(scene)")
    near, far = selection.near, selection.far
    rows, columns = np.flatnonzero(first.has_pose), np.flatnonzero(second.has_pose)
    second_frusta = TruncatedFrusta.of_images(second, columns, near, far)
    rows_per_chunk = max(1, PAIRS_PER_CHUNK // max(1, len(columns)))
    pairs = [np.empty((0, 2), dtype=np.int64)]
    for start in range(0, len(rows), rows_per_chunk):
        chunk = rows[start : start + rows_per_chunk]
        radii = pairwise_overlap_radii(TruncatedFrusta.of_images(first, chunk, near, far), second_frusta)
        if exclude_self:
            radii[chunk[:, None] == columns[None]] = 0.0
        chunk_rows, chunk_columns = np.nonzero(_selected(radii, selection.min_radius, selection.max_per_image))
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


def database_pairs(database: ImageSet, selection: PairSelection) -> np.ndarray:
    """Distinct database pairs ``[P, 2]`` (a < b) of the global map, selected by frustum overlap."""
    pairs = overlapping_pairs(database, database, selection, exclude_self=True)
    return np.unique(np.sort(pairs, axis=1), axis=0)
