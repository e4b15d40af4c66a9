"""`Camera`, `ImageSet` and `Scene`: what every other module reads about a dataset."""

from __future__ import annotations

import functools
import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from locretrieval import geometry
from locretrieval.cache import file_signature
from locretrieval.config import ConfigError, require_part
from locretrieval.scene.ltvl import KaptureNames, LtvlNames
from locretrieval.scene.reconstruction import Observations, ReconstructionQuality

#: The unit of positions and position thresholds of a scene with a metric scale; a reconstruction
#: without one (``data.unitless=true``) is in `MODEL_UNITS`.
METRES = "m"
MODEL_UNITS = "model units"

#: COLMAP camera models and the indices of (fx, fy, cx, cy) in their parameter vectors.
#: Single-focal models repeat the focal length.
CAMERA_MODELS: dict[str, tuple[int, int, int, int]] = {
    "SIMPLE_PINHOLE": (0, 0, 1, 2),
    "PINHOLE": (0, 1, 2, 3),
    "SIMPLE_RADIAL": (0, 0, 1, 2),
    "RADIAL": (0, 0, 1, 2),
    "OPENCV": (0, 1, 2, 3),
    "OPENCV_FISHEYE": (0, 1, 2, 3),
    "FULL_OPENCV": (0, 1, 2, 3),
    "FOV": (0, 1, 2, 3),
    "SIMPLE_RADIAL_FISHEYE": (0, 0, 1, 2),
    "RADIAL_FISHEYE": (0, 0, 1, 2),
    "THIN_PRISM_FISHEYE": (0, 1, 2, 3),
}

#: Number of parameters of each COLMAP camera model.
CAMERA_MODEL_PARAMS: dict[str, int] = {
    "SIMPLE_PINHOLE": 3,
    "PINHOLE": 4,
    "SIMPLE_RADIAL": 4,
    "RADIAL": 5,
    "OPENCV": 8,
    "OPENCV_FISHEYE": 8,
    "FULL_OPENCV": 12,
    "FOV": 5,
    "SIMPLE_RADIAL_FISHEYE": 4,
    "RADIAL_FISHEYE": 5,
    "THIN_PRISM_FISHEYE": 12,
}


@dataclass(frozen=True)
class Camera:
    """Intrinsics in COLMAP's model vocabulary; ``params`` in that model's order, pixels.

    Principal points are kept as the source file states them (COLMAP's convention puts the
    centre of the first pixel at (0.5, 0.5)); the synthetic renderer follows COLMAP.
    """

    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self) -> None:
        if self.model not in CAMERA_MODELS:
            raise ValueError(f"unknown camera model {self.model!r}; expected one of {sorted(CAMERA_MODELS)}")
        expected = CAMERA_MODEL_PARAMS[self.model]
        if len(self.params) != expected:
            raise ValueError(
                f"camera model {self.model} takes {expected} parameters, got {len(self.params)}: {self.params}"
            )
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")

    @property
    def pinhole(self) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)``, ignoring distortion."""
        return tuple(float(self.params[i]) for i in CAMERA_MODELS[self.model])  # type: ignore[return-value]

    def calibration_matrix(self) -> np.ndarray:
        fx, fy, cx, cy = self.pinhole
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


@dataclass
class ImageSet:
    """An ordered set of images with cameras, optional poses and tags.

    ``names`` are paths relative to ``image_root`` (kapture's records_data naming).
    ``qvec``/``tvec`` are world-to-camera poses (wxyz quaternion, translation); rows of an
    image without a known pose are NaN. ``tags`` hold conditions such as ``day``, ``night``,
    ``blur``, ``dynamic`` or the name of the query set an image came from.
    ``depth_paths``/``mask_paths`` are optional per-image files (float32 depth along the
    optical axis; uint8 masks, non-zero on dynamic objects), ``None`` where absent.
    ``image_roots`` (optional) gives each image its own root, for sets read from several
    folders (e.g. Aachen's query_day + query_night); read files through ``paths``.
    """

    names: list[str]
    image_root: Path
    cameras: list[Camera]
    qvec: np.ndarray
    tvec: np.ndarray
    tags: list[frozenset[str]] = field(default_factory=list)
    depth_paths: list[Path | None] | None = None
    mask_paths: list[Path | None] | None = None
    image_roots: list[Path] | None = None

    def __post_init__(self) -> None:
        n = len(self.names)
        self.image_root = Path(self.image_root)
        self.qvec = np.array(self.qvec, dtype=np.float64).reshape(n, 4)  # copies: normalised below
        self.tvec = np.array(self.tvec, dtype=np.float64).reshape(n, 3)
        if not self.tags:
            self.tags = [frozenset() for _ in range(n)]
        for label, values in (
            ("cameras", self.cameras),
            ("tags", self.tags),
            ("depth_paths", self.depth_paths),
            ("mask_paths", self.mask_paths),
            ("image_roots", self.image_roots),
        ):
            if values is not None and len(values) != n:
                raise ValueError(f"ImageSet has {n} names but {len(values)} {label}")
        if len(set(self.names)) != n:
            raise ValueError(f"duplicate image names in ImageSet rooted at {self.image_root}")
        known = self.has_pose
        bad = geometry.invalid_quaternion_rows(self.qvec[known])
        if bad.size:
            name = self.names[np.flatnonzero(known)[bad[0]]]
            raise ValueError(
                f"image {name!r}: pose quaternion {self.qvec[known][bad[0]]} is not a finite unit quaternion"
            )
        if not np.isfinite(self.tvec[known]).all():
            raise ValueError(f"non-finite translation in ImageSet rooted at {self.image_root}")
        self.qvec[known] = geometry.normalize_quaternions(self.qvec[known])

    def __len__(self) -> int:
        return len(self.names)

    @functools.cached_property
    def paths(self) -> list[Path]:
        """Each image's file (built once: callers index it per image)."""
        roots = self.image_roots or [self.image_root] * len(self.names)
        return [root / name for root, name in zip(roots, self.names)]

    @property
    def has_pose(self) -> np.ndarray:
        """Boolean ``[N]``: the image has a known world-to-camera pose."""
        return np.isfinite(self.qvec).all(axis=1) & np.isfinite(self.tvec).all(axis=1)

    @property
    def centers(self) -> np.ndarray:
        """Camera centres ``[N, 3]`` in world coordinates (NaN where the pose is unknown)."""
        return geometry.camera_centers(self.qvec, self.tvec)

    @functools.cached_property
    def intrinsics(self) -> np.ndarray:
        """``[N, 6]`` rows of ``(fx, fy, cx, cy, width, height)``, distortion ignored (built once:
        the frustum ground truth indexes it per block of queries)."""
        return np.array([(*c.pinhole, c.width, c.height) for c in self.cameras], dtype=np.float64)

    def tag_mask(self, tag: str) -> np.ndarray:
        """Boolean ``[N]``: images carrying ``tag``."""
        return np.array([tag in tags for tags in self.tags], dtype=bool)

    @property
    def all_tags(self) -> list[str]:
        return sorted(set().union(*self.tags)) if self.tags else []

    def subset(self, indices: np.ndarray) -> "ImageSet":
        """The images at ``indices`` (or where a boolean mask is true), in that order."""
        indices = np.asarray(indices)
        if indices.dtype == bool:
            indices = np.flatnonzero(indices)

        def pick(values):
            return None if values is None else [values[i] for i in indices]

        return ImageSet(
            names=pick(self.names),
            image_root=self.image_root,
            cameras=pick(self.cameras),
            qvec=self.qvec[indices],
            tvec=self.tvec[indices],
            tags=pick(self.tags),
            depth_paths=pick(self.depth_paths),
            mask_paths=pick(self.mask_paths),
            image_roots=pick(self.image_roots),
        )

    def fingerprint(self, include_poses: bool = True) -> str:
        """Hash of names, cameras, image file sizes and times, and (``include_poses``) poses:
        keys caches of derived data (without poses for what depends on the pixels only)."""
        digest = hashlib.sha256()
        for name, camera, path in zip(self.names, self.cameras, self.paths):
            signature = file_signature(path)
            digest.update(
                f"{name}|{camera.model}|{camera.width}|{camera.height}|{camera.params}|{signature}\n".encode()
            )
        if include_poses:
            digest.update(np.nan_to_num(self.qvec, nan=7.0).round(9).tobytes())
            digest.update(np.nan_to_num(self.tvec, nan=7.0).round(9).tobytes())
        return digest.hexdigest()[:16]


#: How LTVL submission files name images (cf. kapture's ``kapture_export_LTVL2020``):
@dataclass
class Scene:
    """A localisation benchmark: database images with known poses and query images.

    ``sources`` are the folders the scene was read from (e.g. kapture mapping and query
    folders), used to find published side data such as precomputed features. Dataset facts
    the pipeline reads: ``ltvl_names`` (`LtvlNames`, how LTVL submissions name images; kapture's
    names unless given) and ``frustum_far`` (metres, the far plane of the frustum ground truth and of
    global-map pair selection where their config leaves ``far`` null; ``None``: unset) and
    ``unsupported`` (paradigm or ground-truth name -> why this dataset cannot run it, e.g.
    InLoc's global SfM, which the paper builds from depth scans). A scene read from a reconstruction
    (``data=colmap``, ``data=photos``) holds the 3D points its images observe (``observations``, the
    co-observation ground truth's, with no SfM of ours) and its ``quality`` as a pseudo ground truth.
    """

    name: str
    database: ImageSet
    queries: ImageSet
    sources: list[Path] = field(default_factory=list)
    ltvl_names: LtvlNames = field(default_factory=KaptureNames)
    frustum_far: float | None = None
    unsupported: dict[str, str] = field(default_factory=dict)
    observations: Observations | None = None
    quality: ReconstructionQuality | None = None

    def __post_init__(self) -> None:
        self.check_facts(self.name, self.ltvl_names, self.frustum_far)
        if self.observations is not None:
            missing = self.observations.missing([*self.database.names, *self.queries.names])
            if missing:
                raise ValueError(f"scene {self.name!r}: images without observations: {missing[:5]}")
        if len(self.database) == 0:
            raise ValueError(f"scene {self.name!r} has an empty database")
        if not self.database.has_pose.all():
            missing = [n for n, ok in zip(self.database.names, self.database.has_pose) if not ok]
            raise ValueError(f"scene {self.name!r}: database images without pose: {missing[:5]}")

    @property
    def position_unit(self) -> str:
        """The unit of its positions and of the position thresholds: `METRES`, or `MODEL_UNITS` for a
        reconstruction run without a metric scale (``data.unitless=true``)."""
        unitless = self.quality is not None and self.quality.scale_source == "unitless"
        return MODEL_UNITS if unitless else METRES

    def far_plane(self, far: float | None, key: str) -> float:
        """``far`` (metres), or the scene's ``frustum_far`` where ``far`` (the config ``key``) is ``None``."""
        if far is not None:
            return float(far)
        if self.frustum_far is None:
            raise ConfigError(
                f"{key} is null (the dataset's frustum far plane) but scene {self.name!r} has no frustum_far"
            )
        return float(self.frustum_far)

    @staticmethod
    def check_facts(name: str, ltvl_names: LtvlNames, frustum_far: float | None) -> None:
        """Raise unless ``ltvl_names`` is an `LtvlNames` and ``frustum_far`` is ``None`` or a
        positive number of metres."""
        require_part(ltvl_names, LtvlNames, "data.ltvl_names", "data/ltvl_names")
        if frustum_far is not None and not float(frustum_far) > 0:
            raise ValueError(f"dataset {name!r}: frustum_far must be a positive distance in metres, got {frustum_far}")
