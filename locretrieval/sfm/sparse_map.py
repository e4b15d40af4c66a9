"""`SparseMap`: 3D points and the keypoints observing them, per image."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from locretrieval.cache import load_arrays, save_arrays


@dataclass
class SparseMap:
    """3D points ``[P, 3]`` (world coordinates) and, per image, the point each keypoint observes.

    ``observations[i]`` is ``int64 [n_i]`` over image ``i``'s keypoints: a row of ``points``
    or -1 where the keypoint observes no point. A map loaded with ``memory_map`` reads from its
    file only what is used (``source``: that file), and is pickled as that file's name: a worker
    process given the map maps the file itself, so registering a query reads the observations of
    its top-k images and the points they see, not the whole map.
    """

    points: np.ndarray
    observations: list[np.ndarray]
    source: Path | None = field(default=None, compare=False)

    @property
    def num_points(self) -> int:
        return len(self.points)

    def save(self, path: str | Path) -> None:
        lengths = [len(ids) for ids in self.observations]
        flat = np.concatenate(self.observations) if self.observations else np.empty(0, dtype=np.int64)
        save_arrays(path, {"points": self.points, "observations": flat, "lengths": np.asarray(lengths, dtype=np.int64)})

    @classmethod
    def load(cls, path: str | Path, memory_map: bool = False) -> "SparseMap":
        """The map saved at ``path``; with ``memory_map``, its arrays mapped read-only (`load_arrays`)."""
        arrays = load_arrays(path, memory_map=memory_map)
        bounds = np.cumsum(arrays["lengths"])[:-1]
        return cls(arrays["points"], np.split(arrays["observations"], bounds), Path(path) if memory_map else None)

    def __reduce__(self):
        if self.source is not None:  # memory-mapped: the file's name, mapped again where it is unpickled
            return SparseMap.load, (self.source, True)
        return SparseMap, (self.points, self.observations)

    def observed_points(self) -> list[np.ndarray]:
        """Per image, the distinct points it observes (sorted)."""
        return [np.unique(ids[ids >= 0]) for ids in self.observations]
