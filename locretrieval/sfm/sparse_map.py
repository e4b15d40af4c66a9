"""`SparseMap`: 3D points and the keypoints observing them, per image."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from locretrieval.cache import load_arrays, save_arrays


@dataclass
class SparseMap:
    """3D points ``[P, 3]`` (world coordinates) and, per image, the point each keypoint observes.

    ``observations[i]`` is ``int64 [n_i]`` over image ``i``'s keypoints: a row of ``points``
    or -1 where the keypoint observes no point.
    """

    points: np.ndarray
    observations: list[np.ndarray]

    @property
    def num_points(self) -> int:
        return len(self.points)

    def save(self, path: str | Path) -> None:
        lengths = [len(ids) for ids in self.observations]
        flat = np.concatenate(self.observations) if self.observations else np.empty(0, dtype=np.int64)
        save_arrays(path, {"points": self.points, "observations": flat, "lengths": np.asarray(lengths, dtype=np.int64)})

    @classmethod
    def load(cls, path: str | Path) -> "SparseMap":
        arrays = load_arrays(path)
        bounds = np.cumsum(arrays["lengths"])[:-1]
        return cls(arrays["points"], np.split(arrays["observations"], bounds))

    def observed_points(self) -> list[np.ndarray]:
        """Per image, the distinct points it observes (sorted)."""
        return [np.unique(ids[ids >= 0]) for ids in self.observations]
