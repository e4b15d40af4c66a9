"""The metric scale of a reconstruction: the paradigms' thresholds are metres, a reconstruction's
units are whatever its first two images made them. Never silently wrong: the scale comes from
``data.metres_per_unit``, from one known distance between two named images
(``data.known_distance``), or from the GPS positions in the photos' EXIF (a similarity alignment to
them, pycolmap's ``align_reconstruction_to_locations``); without any of them the run stops naming the
three ways (``data.unitless=true`` accepts the model's units on purpose, and the results say so).

Positions from GPS are local east-north-up metres about the mean GPS position (pycolmap's
``GPSTransform``, GRS80); the aligned scene's world frame is that one.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import ExifTags, Image, UnidentifiedImageError

from locretrieval.config import ConfigError, require
from locretrieval.errors import DataFileError

log = logging.getLogger(__name__)

#: Images with a GPS position an alignment needs at least (a similarity has 7 degrees of freedom).
MIN_GPS_IMAGES = 3
#: GPS altitudes (metres) a photo can hold: the deepest sea floor to above the highest summit. An
#: altitude outside (4.29e9 m: an unsigned field that wrapped) makes its position an outlier.
EARTH_ALTITUDES_M = (-11_000.0, 9_000.0)


@dataclass
class KnownDistance:
    """The distance in ``metres`` between the camera centres of the two ``images`` (names relative
    to the image folder)."""

    images: list[str]
    metres: float

    def __post_init__(self) -> None:
        require(
            len(self.images) == 2 and self.images[0] != self.images[1],
            "images",
            f"must name two different images, got {self.images}",
        )
        require(math.isfinite(self.metres) and self.metres > 0, "metres", f"must be positive, got {self.metres}")


@dataclass
class ScaleSettings:
    """How a reconstruction's units become metres: ``metres_per_unit``, ``known_distance`` or
    ``unitless`` (at most one of them; none: GPS in the images' EXIF); ``gps_max_error`` (metres):
    GPS positions farther than this from the aligned camera centres are outliers of the alignment."""

    metres_per_unit: float | None
    known_distance: KnownDistance | None
    unitless: bool
    gps_max_error: float

    def __post_init__(self) -> None:
        given = self.explicit()
        if len(given) > 1:
            raise ConfigError(f"data.{given[0]} and data.{given[1]} both set the scale: give one of them")
        require(
            self.metres_per_unit is None or (math.isfinite(self.metres_per_unit) and self.metres_per_unit > 0),
            "metres_per_unit",
            f"must be a positive number of metres per model unit, got {self.metres_per_unit}",
        )
        require(self.gps_max_error > 0, "gps_max_error", f"must be positive metres, got {self.gps_max_error}")

    def explicit(self) -> list[str]:
        """The keys that set the scale (no GPS then)."""
        keys = {
            "metres_per_unit": self.metres_per_unit is not None,
            "known_distance": self.known_distance is not None,
            "unitless": self.unitless,
        }
        return [key for key, given in keys.items() if given]


@dataclass(frozen=True)
class MetricAlignment:
    """The similarity that takes a reconstruction to metres (``new_from_old``, a ``pycolmap.Sim3d``),
    where it came from (``source``: ``gps``, ``metres_per_unit``, ``known_distance`` or
    ``unitless``), and for GPS the images with a position and the residual distances (metres)
    between their aligned centres and their GPS positions."""

    new_from_old: Any
    source: str
    gps_images: int = 0
    gps_residuals: np.ndarray | None = None

    @property
    def metres_per_unit(self) -> float:
        return float(self.new_from_old.scale)


def metric_alignment(
    reconstruction: Any, image_folder: Path, names: Sequence[str], settings: ScaleSettings, model: str
) -> MetricAlignment:
    """The alignment of ``reconstruction`` (a ``pycolmap.Reconstruction``; ``names``: its
    registered images, files of ``image_folder``) to metres as ``settings`` say; ``model`` names it
    in errors. Raises `ConfigError` when nothing gives the scale."""
    import pycolmap

    explicit = settings.explicit()
    if explicit:
        if explicit[0] == "unitless":
            log.warning("%s: data.unitless=true: positions and thresholds are in the model's units, not metres", model)
            return MetricAlignment(pycolmap.Sim3d(), "unitless")
        scale = settings.metres_per_unit or _known_distance_scale(reconstruction, settings.known_distance, model)
        return MetricAlignment(pycolmap.Sim3d(scale, pycolmap.Rotation3d(), np.zeros(3)), explicit[0])
    positions, outliers = _on_earth(gps_positions(image_folder, names), model)
    if len(positions) < MIN_GPS_IMAGES:
        off_earth = f"; {outliers} more hold altitudes outside Earth's {EARTH_ALTITUDES_M} m" if outliers else ""
        raise ConfigError(
            f"the scale of {model} is unknown, and the paradigms' thresholds are metres. Give it one of three ways:\n"
            f"  1. GPS positions in the photos' EXIF (found in {len(positions)} of the {len(names)} registered "
            f"images{off_earth}; at least {MIN_GPS_IMAGES} are needed),\n"
            "  2. data.metres_per_unit=<metres per model unit>,\n"
            "  3. 'data.known_distance={images: [<image a>, <image b>], metres: <their distance>}' (two registered "
            "images' camera centres).\n"
            "(data.unitless=true runs with the model's units on purpose; the results say so.)"
        )
    return _gps_alignment(reconstruction, positions, settings.gps_max_error, model, image_folder)


def _on_earth(positions: dict[str, np.ndarray], model: str) -> tuple[dict[str, np.ndarray], int]:
    """``positions`` whose altitude is unknown (NaN) or within `EARTH_ALTITUDES_M`, and how many
    others there are: outliers (logged)."""
    low, high = EARTH_ALTITUDES_M
    outliers = {name: position for name, position in positions.items() if position[2] < low or position[2] > high}
    if outliers:
        name, position = next(iter(outliers.items()))
        log.warning(
            "%s: %d GPS positions have altitudes outside Earth's %s m (e.g. %s: %.6g m) and are left out of the "
            "alignment as outliers",
            model,
            len(outliers),
            EARTH_ALTITUDES_M,
            name,
            position[2],
        )
    return {name: position for name, position in positions.items() if name not in outliers}, len(outliers)


def _known_distance_scale(reconstruction: Any, known: KnownDistance, model: str) -> float:
    """Metres per unit from the distance of two registered images' camera centres."""
    centres = []
    for name in known.images:
        image = reconstruction.find_image_with_name(name)
        if image is None or not image.has_pose:
            raise ConfigError(f"data.known_distance.images: {name!r} is not a registered image of {model}")
        centres.append(np.asarray(image.projection_center()))
    units = float(np.linalg.norm(centres[0] - centres[1]))
    if not units > 0:
        raise ConfigError(f"data.known_distance.images: {known.images} have the same camera centre in {model}")
    return known.metres / units


def _gps_alignment(
    reconstruction: Any, positions: dict[str, np.ndarray], max_error: float, model: str, image_folder: Path
) -> MetricAlignment:
    """The similarity taking the camera centres to the GPS positions (east-north-up metres), and its
    residuals; refused (`DataFileError` naming the photos' folder) when most of them exceed
    ``max_error``: GPS and model disagree, and a scale fitted to them would be wrong."""
    import pycolmap

    names = sorted(positions)
    lat_lon_alt = np.array([positions[name] for name in names])
    if np.isnan(lat_lon_alt[:, 2]).any():
        log.warning("%s: some GPS positions have no altitude; aligning all at altitude 0", model)
        lat_lon_alt[:, 2] = 0.0
    origin = lat_lon_alt.mean(axis=0)
    enu = np.asarray(pycolmap.GPSTransform().ellipsoid_to_enu(lat_lon_alt, *origin))
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = max_error
    new_from_old = pycolmap.align_reconstruction_to_locations(reconstruction, names, enu, MIN_GPS_IMAGES, ransac)
    if new_from_old is None:
        raise ConfigError(
            f"the GPS positions of {len(names)} images of {model} could not be aligned to its camera centres "
            f"(collinear positions, or none within data.gps_max_error={max_error} m); give the scale by "
            "data.metres_per_unit or data.known_distance instead"
        )
    old = np.array([reconstruction.find_image_with_name(name).projection_center() for name in names])
    aligned = old @ np.asarray(new_from_old.matrix())[:, :3].T + np.asarray(new_from_old.matrix())[:, 3]
    residuals = np.linalg.norm(aligned - enu, axis=1)
    far = int((residuals > max_error).sum())
    if 2 * far > len(names):
        raise DataFileError(
            image_folder,
            f"the GPS positions of {far} of its {len(names)} images with GPS lie farther than data.gps_max_error="
            f"{max_error} m from the camera centres of {model} aligned to them (residuals: median "
            f"{np.median(residuals):.4g} m, largest {residuals.max():.4g} m, {new_from_old.scale:.4g} metres per "
            "model unit): the GPS and the model disagree, and a scale fitted to them would be wrong. Give the scale "
            "by data.metres_per_unit or data.known_distance, or raise data.gps_max_error for GPS that coarse",
        )
    return MetricAlignment(new_from_old, "gps", len(names), residuals)


def gps_positions(folder: Path, names: Sequence[str]) -> dict[str, np.ndarray]:
    """``name -> (latitude, longitude, altitude)`` (degrees, degrees, metres; altitude NaN when
    absent) of the images of ``folder`` whose EXIF holds a GPS position. GPS data that cannot be
    read is logged and the image counted as without one."""
    positions = {}
    for name in names:
        path = folder / name
        try:
            with Image.open(path) as image:
                gps = image.getexif().get_ifd(ExifTags.IFD.GPSInfo)
        except (UnidentifiedImageError, OSError, Image.DecompressionBombError):
            continue  # the image itself was checked where it was read; no EXIF
        if not gps:
            continue
        try:
            positions[name] = _exif_position(gps)
        except (KeyError, TypeError, ValueError, ZeroDivisionError) as error:
            log.warning("%s: GPS in EXIF not readable (%s): the image counts as without GPS", path, error)
    return positions


def _exif_position(gps: dict) -> np.ndarray:
    """``(latitude, longitude, altitude)`` of an EXIF GPS directory (tags 1-6; altitude NaN when absent)."""

    def degrees(value: Sequence, reference: str, negative: str) -> float:
        d, m, s = (float(part) for part in value)
        angle = d + m / 60.0 + s / 3600.0
        return -angle if str(reference).strip().upper() == negative else angle

    latitude = degrees(gps[ExifTags.GPS.GPSLatitude], gps[ExifTags.GPS.GPSLatitudeRef], "S")
    longitude = degrees(gps[ExifTags.GPS.GPSLongitude], gps[ExifTags.GPS.GPSLongitudeRef], "W")
    if not (-90.0 <= latitude <= 90.0 and -180.0 <= longitude <= 180.0):
        raise ValueError(f"latitude {latitude}, longitude {longitude} out of range")
    altitude = float("nan")
    if ExifTags.GPS.GPSAltitude in gps:
        below = gps.get(ExifTags.GPS.GPSAltitudeRef, b"\x00") in (b"\x01", 1, "1")
        altitude = -float(gps[ExifTags.GPS.GPSAltitude]) if below else float(gps[ExifTags.GPS.GPSAltitude])
    return np.array([latitude, longitude, altitude])
