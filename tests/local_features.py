"""The rendered scene, SfM settings and local features the tests of the SfM stages share, and ternary
descriptors with ties (support module)."""

from dataclasses import dataclass
from pathlib import Path

import helpers
import numpy as np

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.sfm.features import LocalFeatures
from locretrieval.sfm.verification import (
    PoseVerification,
    TwoViewVerification,
)

SCENE = {
    "width": 256,
    "height": 192,
    "num_database": 40,
    "num_queries": 6,
    "texture_size": 128,
    "length": 20.0,
    "conditions": {"night": 0.0, "blur": 0.0, "dynamic": 0.0, "noise": 0.0},
    "database_dynamic": 0.0,
    "hard_query_fraction": 0.0,
    "workers": 1,
    "seed": 1,
}


SFM = helpers.sfm_settings()


POSES, TWO_VIEW = PoseVerification(4.0), TwoViewVerification(4.0, 15)


def features(overrides, kind="sift"):
    """The local features ``sfm/features=<kind>`` with ``overrides``."""
    return helpers.sfm_settings({"features": overrides}, choices=[f"sfm/features={kind}"]).features


def ternary(count: int, dimension: int, nonzero: int, rng: np.random.Generator) -> np.ndarray:
    """Rows of ``nonzero`` entries +-1 (a power of 4, so that normalised rows hold powers of two
    and every similarity is exact in float16, float32 and float64): many exact ties."""
    rows = np.zeros((count, dimension))
    for row in rows:
        row[rng.choice(dimension, nonzero, replace=False)] = rng.choice([-1.0, 1.0], nonzero)
    return rows


@dataclass
class GridFeatures(LocalFeatures):
    """A kind of local features from outside the package: keypoints on a grid of ``step`` px,
    each a descriptor of its grid cell (so images of one camera match cell for cell)."""

    max_keypoints: int | None
    step: int

    def identity(self) -> dict:
        return {"type": "grid", "step": self.step, "max_keypoints": self.max_keypoints}

    def records(self):
        def record(name: str, path: Path) -> dict[str, np.ndarray]:
            xy = np.stack(np.meshgrid(np.arange(8, 200, self.step), np.arange(8, 150, self.step)), -1).reshape(-1, 2)
            cells = np.random.default_rng(0).normal(size=(len(xy), 16)).astype(np.float32)
            return {"keypoints": xy.astype(np.float32), "descriptors": cells}

        return record

    def _best_rows(self, keypoints: np.ndarray, budget: int) -> np.ndarray:
        return np.arange(budget)  # the grid's first cells
