"""What a scene read from a reconstruction (``data=colmap``, ``data=photos``) knows besides its poses:
the 3D points each image observes (the reconstruction's tracks) and how good that pseudo ground
truth is (the paper's caveat for Aachen's and InLoc's reference poses, Sec. 4.1)."""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import sparse


@dataclass(frozen=True)
class Observations:
    """Which 3D points each image observes: ``incidence`` is a boolean sparse ``[images, points]``
    matrix whose rows are the images ``names`` (a reconstruction's tracks). Images are looked up by
    name, so that any subset or order of the scene's images can be asked for."""

    names: list[str]
    incidence: sparse.csr_matrix

    def __post_init__(self) -> None:
        if self.incidence.shape[0] != len(self.names):
            raise ValueError(f"Observations: {len(self.names)} names for {self.incidence.shape[0]} incidence rows")
        if len(set(self.names)) != len(self.names):
            raise ValueError("Observations: duplicate image names")

    @property
    def num_points(self) -> int:
        return self.incidence.shape[1]

    def missing(self, names: Sequence[str]) -> list[str]:
        """The ``names`` without a row."""
        rows = self._rows
        return [name for name in names if name not in rows]

    def rows(self, names: Sequence[str]) -> sparse.csr_matrix:
        """The incidence rows of ``names``, in that order (``int64``, 1 where observed)."""
        missing = self.missing(names)
        if missing:
            raise KeyError(f"{len(missing)} image(s) are not in the reconstruction's observations, e.g. {missing[:3]}")
        rows = self._rows
        return self.incidence[[rows[name] for name in names]].astype(np.int64)

    def shared(self, rows: Sequence[str], columns: Sequence[str]) -> sparse.csr_matrix:
        """``[len(rows), len(columns)]`` number of 3D points observed by both images of each pair."""
        return (self.rows(rows) @ self.rows(columns).T).tocsr()

    def fingerprint(self) -> str:
        """Hash of the names and the incidence (part of the cache key of what is derived from them)."""
        digest = hashlib.sha256("\n".join(self.names).encode())
        incidence = self.incidence.tocsr()
        incidence.sort_indices()
        for array in (incidence.indptr, incidence.indices):
            digest.update(np.ascontiguousarray(array, dtype=np.int64).tobytes())
        return digest.hexdigest()[:16]

    @functools.cached_property
    def _rows(self) -> dict[str, int]:
        return {name: row for row, name in enumerate(self.names)}


#: How a reconstruction's scale became metres (`ReconstructionQuality.scale_source`).
SCALE_SOURCES = ("gps", "metres_per_unit", "known_distance", "unitless")


@dataclass(frozen=True)
class ReconstructionQuality:
    """How good a reconstruction is as a pseudo ground truth: ``images`` found (the folder's image
    files and the model's images), ``registered`` of them (the scene's), its ``points``, their
    ``mean_track_length`` (images per point) and ``mean_reprojection_error_px``; where its scale came
    from (``scale_source``, one of `SCALE_SOURCES`) and ``metres_per_unit`` applied; for GPS, the
    images with a GPS position (``gps_images``) and the distances (metres) between those positions
    and the aligned camera centres (``gps_residual_median_m``, ``gps_residual_rms_m``). ``source``:
    the model folder read."""

    source: str
    images: int
    registered: int
    points: int
    mean_track_length: float
    mean_reprojection_error_px: float
    scale_source: str
    metres_per_unit: float
    gps_images: int = 0
    gps_residual_median_m: float | None = None
    gps_residual_rms_m: float | None = None

    def __post_init__(self) -> None:
        if self.scale_source not in SCALE_SOURCES:
            raise ValueError(f"scale_source must be one of {SCALE_SOURCES}, got {self.scale_source!r}")

    @property
    def registered_share(self) -> float:
        return self.registered / self.images if self.images else 0.0

    def scale_text(self) -> str:
        """Where the metres come from, in words."""
        if self.scale_source == "gps":
            return (
                f"GPS of {self.gps_images} images (alignment residual median {self.gps_residual_median_m:.2f} m, "
                f"RMS {self.gps_residual_rms_m:.2f} m)"
            )
        if self.scale_source == "unitless":
            return "none (data.unitless=true): positions and thresholds are in the model's units, not metres"
        return f"data.{self.scale_source} ({self.metres_per_unit:.6g} metres per model unit)"

    def summary(self) -> dict[str, object]:
        """The figures a reader judges the thresholds against (``summary.json``, the report)."""
        return {
            "model": self.source,
            "registered images": f"{self.registered} of {self.images} ({100 * self.registered_share:.1f} %)",
            "3D points": self.points,
            "mean track length": round(self.mean_track_length, 2),
            "mean reprojection error (px)": round(self.mean_reprojection_error_px, 3),
            "scale": self.scale_text(),
            "metres per model unit": None if self.scale_source == "unitless" else self.metres_per_unit,
            "GPS residual median (m)": self.gps_residual_median_m,
            "GPS residual RMS (m)": self.gps_residual_rms_m,
        }

    def describe(self) -> str:
        """One line for the log."""
        return (
            f"pseudo ground truth {self.source}: {self.registered} of {self.images} images registered "
            f"({100 * self.registered_share:.1f} %), {self.points} points, mean track length "
            f"{self.mean_track_length:.2f}, mean reprojection error {self.mean_reprojection_error_px:.3f} px; "
            f"scale: {self.scale_text()}"
        )
