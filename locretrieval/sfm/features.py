"""The features stage of the SfM pipeline: local features of an image set, cached on disk.

Keypoints are ``float32 [n, 2]`` pixel coordinates in the full-resolution image, in COLMAP's
convention (the centre of the first pixel is (0.5, 0.5)), the convention of `Camera`.
Descriptors are ``[n, D]`` as produced (pycolmap: uint8 RootSIFT scaled by 512; kapture:
the stored dtype).

The local features are an object chosen by ``_target_`` (``sfm/features=sift|kapture|...``), a
`LocalFeatures`:

- `SiftFeatures`: pycolmap's SIFT; ``max_side`` (px; images whose longer side exceeds it are
  downscaled for extraction, keypoints scaled back), ``first_octave``, ``max_num_features``,
  ``peak_threshold`` (pycolmap's SIFT options);
- `KaptureFeatures`: precomputed features ``name`` of the kapture folder each image comes from
  (``reconstruction/keypoints/<name>/<image>.kpt`` and ``descriptors/<name>/<image>.desc``
  with their ``keypoints.txt``/``descriptors.txt`` headers, or the downloader's
  ``<dataset>/local_features/<name>/{keypoints,descriptors}/``, e.g. the published R2D2
  features ``r2d2_WASF-N8_20k``: ``sfm=r2d2_published``); ``pixel_offset`` is added to their x
  and y (0.5 converts keypoints whose first pixel centre is (0, 0), as R2D2 and OpenCV write
  them, to COLMAP's convention); ``score_order`` says how the rows are ordered by detector
  score (R2D2: ascending).

``max_keypoints`` (every kind; null: all) keeps each image's best keypoints: the best rows by
score for kapture features, pycolmap's strongest detections for SIFT (`LocalFeatures.best_rows`).
A new kind is a `LocalFeatures` subclass (``identity``, ``records``, ``best_rows``) and a YAML.

Features live in ``<cache_dir>/features/<image set fingerprint>-<config key>/`` as HDF5
shards (`ShardedStore`) keyed by image name, computed once and reused across runs.
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from locretrieval.cache import config_key
from locretrieval.config import require
from locretrieval.pool import WORKERS, resolve_workers, split
from locretrieval.scene import ImageSet
from locretrieval.scene.images import read_image
from locretrieval.sfm.store import ShardedStore

log = logging.getLogger(__name__)

SIFT_DIMENSION = 128
#: Images per shard (one task of a worker).
IMAGES_PER_SHARD = 32
#: Bump when the meaning of cached features changes.
CACHE_VERSION = 1


class LocalFeatures(abc.ABC):
    """Local features of images, keeping each image's ``max_keypoints`` best (None: all)."""

    max_keypoints: int | None

    @abc.abstractmethod
    def identity(self) -> dict[str, Any]:
        """What determines the features (the cache key)."""

    @abc.abstractmethod
    def records(self) -> Callable[[str, Path], dict[str, np.ndarray]]:
        """``(image name, path) -> {"keypoints", "descriptors"}``, every keypoint (in a worker process)."""

    def best_rows(self, keypoints: np.ndarray) -> np.ndarray:
        """Sorted row indices of the at most ``max_keypoints`` best of ``keypoints [n, >=2]``
        (every row when the budget is None or not exceeded; `_best_rows` otherwise)."""
        if self.max_keypoints is None or len(keypoints) <= self.max_keypoints:
            return np.arange(len(keypoints))
        return self._best_rows(keypoints, self.max_keypoints)

    @abc.abstractmethod
    def _best_rows(self, keypoints: np.ndarray, budget: int) -> np.ndarray:
        """Sorted row indices of the ``budget`` best of more than ``budget`` ``keypoints``."""

    def missing_inputs(self, images: ImageSet) -> list[str]:
        """What reading the features of ``images`` would miss (files it reads)."""
        return []

    def key(self) -> str:
        """Cache key of the features."""
        return config_key(CACHE_VERSION, self.identity())

    def _check_budget(self) -> None:
        require(
            self.max_keypoints is None or self.max_keypoints > 0,
            "max_keypoints",
            f"must be positive or null, got {self.max_keypoints}",
        )


@dataclass
class SiftFeatures(LocalFeatures):
    """pycolmap SIFT: images whose longer side exceeds ``max_side`` px are downscaled for
    extraction (keypoints scaled back); ``first_octave``, ``max_num_features`` and
    ``peak_threshold`` are pycolmap's SIFT options; at most ``max_keypoints`` detections."""

    max_keypoints: int | None
    max_side: int
    first_octave: int
    max_num_features: int
    peak_threshold: float

    def __post_init__(self) -> None:
        self._check_budget()
        require(self.max_side > 0, "max_side", f"must be a positive number of pixels, got {self.max_side}")
        require(self.max_num_features > 0, "max_num_features", f"must be positive, got {self.max_num_features}")
        require(self.peak_threshold > 0, "peak_threshold", f"must be positive, got {self.peak_threshold}")

    def identity(self) -> dict[str, Any]:
        options = {
            key: getattr(self, key) for key in ("max_side", "first_octave", "max_num_features", "peak_threshold")
        }
        return {"type": "sift", "max_keypoints": self.max_keypoints, "sift": options}

    def records(self) -> Callable[[str, Path], dict[str, np.ndarray]]:
        extract = _sift_extractor(self, self.max_keypoints)
        return lambda name, path: extract(path)

    def _best_rows(self, keypoints: np.ndarray, budget: int) -> np.ndarray:
        """pycolmap already kept its strongest detections (``max_num_features``), but a detection
        with two orientations is two rows: each location's first row comes before the extra
        orientations, in pycolmap's order."""
        _, first = np.unique(keypoints[:, :2], axis=0, return_index=True)
        extra_orientations = np.setdiff1d(np.arange(len(keypoints)), first)
        return np.sort(np.concatenate([np.sort(first), extra_orientations])[:budget])


#: How the rows of a kapture keypoints file are ordered by detector score (R2D2's
#: ``extract_kapture.py`` keeps the top-k by score in ascending order: the best rows last).
SCORE_ORDERS = ("ascending", "descending")


@dataclass
class KaptureFeatures(LocalFeatures):
    """Published features ``name`` of each kapture folder (``reconstruction/{keypoints,descriptors}/<name>/``
    or the downloader's ``local_features/<name>/{keypoints,descriptors}/`` beside it); ``pixel_offset``
    is added to their x and y (0.5: OpenCV/R2D2 pixel centres to COLMAP's); ``score_order``: how
    their rows are ordered by detector score (`SCORE_ORDERS`, or null: unknown, then no ``max_keypoints``)."""

    max_keypoints: int | None
    name: str
    pixel_offset: float
    score_order: str | None

    def __post_init__(self) -> None:
        self._check_budget()
        require(
            self.score_order is None or self.score_order in SCORE_ORDERS,
            "score_order",
            f"must be one of {list(SCORE_ORDERS)} or null, got {self.score_order!r}",
        )
        require(
            self.max_keypoints is None or self.score_order is not None,
            "max_keypoints",
            f"needs the score order of the kapture features {self.name!r} (sfm.features.score_order: "
            f"{' or '.join(SCORE_ORDERS)}), which is not set",
        )

    def identity(self) -> dict[str, Any]:
        options = {"name": self.name, "pixel_offset": self.pixel_offset, "score_order": self.score_order}
        return {"type": "kapture", "max_keypoints": self.max_keypoints, "kapture": options}

    def records(self) -> Callable[[str, Path], dict[str, np.ndarray]]:
        return partial(_read_kapture_features, settings=self)

    def _best_rows(self, keypoints: np.ndarray, budget: int) -> np.ndarray:
        """The rows are ordered by detector score (``score_order``): the best are the last
        (ascending) or the first (descending)."""
        start = len(keypoints) - budget if self.score_order == "ascending" else 0
        return np.arange(start, start + budget)

    def missing_inputs(self, images: ImageSet) -> list[str]:
        return missing_kapture_features(images, self)


class FeatureStore:
    """Cached local features of one image set: ``keypoints`` and ``descriptors`` by image name."""

    def __init__(self, folder: str | Path) -> None:
        self.store = ShardedStore(folder)

    @property
    def folder(self) -> Path:
        return self.store.folder

    def load(self, names: Sequence[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """``name -> (keypoints float32 [n, 2], descriptors [n, D])``."""
        return {name: (r["keypoints"], r["descriptors"]) for name, r in self.store.read(names).items()}

    def keypoints(self, names: Sequence[str]) -> dict[str, np.ndarray]:
        """``name -> keypoints float32 [n, 2]``, without reading the descriptors."""
        return {name: record["keypoints"] for name, record in self.store.read(names, arrays=("keypoints",)).items()}


def feature_store(images: ImageSet, settings: LocalFeatures, cache_dir: str | Path) -> FeatureStore:
    """Where the features of ``images`` are cached (as far as they are: nothing is extracted)."""
    return FeatureStore(Path(cache_dir) / "features" / f"{images.fingerprint(include_poses=False)}-{settings.key()}")


def extract_features(
    images: ImageSet, settings: LocalFeatures, cache_dir: str | Path, workers: int, names: Sequence[str] | None = None
) -> FeatureStore:
    """The features of every image of ``images`` (or of those ``names``), extracting (or reading)
    only missing ones."""
    store = feature_store(images, settings, cache_dir)
    paths = dict(zip(images.names, images.paths))
    missing = store.store.missing(images.names if names is None else names)
    if missing:
        log.info("local features (%s) of %d images into %s", type(settings).__name__, len(missing), store.folder)
        chunks = split(missing, IMAGES_PER_SHARD, resolve_workers(workers))
        tasks = [[(name, str(paths[name])) for name in chunk] for chunk in chunks]
        shared = (str(store.folder), settings)
        for _ in WORKERS.map(
            _extract_shard, tasks, workers, f"features ({type(settings).__name__})", shared, units=len
        ):
            pass
        store.store.refresh()
    return store


def _extract_shard(shared: tuple[str, LocalFeatures], images: list[tuple[str, str]]) -> int:
    """Worker: features of one chunk of ``(name, image path)``, written as one shard."""
    folder, settings = shared
    features = read_or_extract(settings)
    ShardedStore(folder).write({name: features(name, Path(path)) for name, path in images})
    return len(images)


def read_or_extract(settings: LocalFeatures) -> Callable[[str, Path], dict[str, np.ndarray]]:
    """``(image name, path) -> {"keypoints", "descriptors"}`` of ``settings``, the best
    ``max_keypoints`` of them (`LocalFeatures.best_rows`), in memory (nothing is cached)."""
    source = settings.records()

    def features(name: str, path: Path) -> dict[str, np.ndarray]:
        record = source(name, path)
        kept = settings.best_rows(record["keypoints"])
        return {key: values[kept] for key, values in record.items()}

    return features


def _sift_extractor(settings: SiftFeatures, budget: int | None) -> Callable[[Path], dict[str, np.ndarray]]:
    """``path -> {"keypoints", "descriptors"}`` with pycolmap's CPU SIFT (at most ``budget``
    detections, when it is below ``max_num_features``)."""
    import pycolmap

    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = 1
    options.sift.first_octave = settings.first_octave
    options.sift.max_num_features = min(settings.max_num_features, budget or settings.max_num_features)
    options.sift.peak_threshold = settings.peak_threshold
    extractor = pycolmap.FeatureExtractor.create(options)
    max_side = settings.max_side

    def extract(path: Path) -> dict[str, np.ndarray]:
        image = read_image(path, grayscale=True)
        height, width = image.shape
        scale = min(1.0, max_side / max(height, width))
        if scale < 1.0:
            size = (max(1, round(width * scale)), max(1, round(height * scale)))
            image = np.asarray(Image.fromarray(image).resize(size, Image.Resampling.LANCZOS))
        keypoints, descriptors = extractor.extract_from_uint8_array(np.ascontiguousarray(image))
        xy = pycolmap.keypoints_to_matrix(keypoints)[:, :2].astype(np.float64)
        # COLMAP coordinates start at the image corner, so resizing is a pure scale per axis.
        xy *= np.array([width / image.shape[1], height / image.shape[0]])
        return {
            "keypoints": xy.astype(np.float32),
            "descriptors": np.asarray(descriptors.data, dtype=np.uint8).reshape(len(xy), SIFT_DIMENSION),
        }

    return extract


def kapture_root_of(image_path: Path, name: str) -> Path:
    """The kapture folder of an image at ``<kapture>/sensors/records_data/<name>``."""
    records_data = Path(str(image_path)[: -len(name)]) if str(image_path).endswith(name) else None
    if records_data is None or records_data.parts[-2:] != ("sensors", "records_data"):
        raise ValueError(f"image {image_path} is not inside a kapture folder's sensors/records_data/")
    return records_data.parent.parent


#: The kapture local-feature kinds.
KAPTURE_FEATURE_KINDS = ("keypoints", "descriptors")


def kapture_feature_folder(root: Path, kind: str, features: str) -> Path:
    """The folder of the ``kind`` features ``features`` of kapture folder ``root``, in kapture's
    layout or the downloader's (`find_feature_folder`); FileNotFoundError naming both otherwise."""
    from locretrieval.scene import feature_files  # here: kapture's imports (seconds) only where its features are read

    folder = feature_files.find_feature_folder(root, kind, features)
    if folder is None:
        searched = [str(f / f"{kind}.txt") for f in feature_files.feature_folder_candidates(root, kind, features)]
        raise FileNotFoundError(f"kapture {kind} {features!r} of {root} not found: none of {searched}")
    return folder


def missing_kapture_features(images: ImageSet, settings: KaptureFeatures) -> list[str]:
    """What reading the kapture features of ``images`` would miss: each absent feature folder, and
    per kapture folder the images without a keypoints or descriptors file (counted, one named)."""
    from locretrieval.scene import feature_files  # here: kapture's imports (seconds) only where its features are read

    names_by_root: dict[Path, list[str]] = {}
    for name, path in zip(images.names, images.paths):
        names_by_root.setdefault(kapture_root_of(path, name), []).append(name)
    problems = []
    for root, names in names_by_root.items():
        for kind in KAPTURE_FEATURE_KINDS:
            try:
                folder = kapture_feature_folder(root, kind, settings.name)
            except FileNotFoundError as error:
                problems.append(str(error))
                continue
            absent = [
                path for path in (feature_files.feature_file(folder, kind, n) for n in names) if not path.is_file()
            ]
            if absent:
                problems.append(
                    f"kapture {kind} {settings.name!r}: {len(absent)} of "
                    f"{len(names)} images lack their file, e.g. {absent[0]}"
                )
    return problems


def _read_kapture_features(image_name: str, image_path: Path, settings: KaptureFeatures) -> dict[str, np.ndarray]:
    """Keypoints (x, y shifted by ``pixel_offset``) and descriptors of one image from kapture files."""
    from locretrieval.scene import feature_files  # here: kapture's imports (seconds) only where its features are read

    root = kapture_root_of(image_path, image_name)
    features = settings.name
    arrays = {}
    for kind in KAPTURE_FEATURE_KINDS:
        folder = kapture_feature_folder(root, kind, features)
        config = feature_files.read_feature_header(folder / f"{kind}.txt", kind)
        path = feature_files.feature_file(folder, kind, image_name)
        if not path.is_file():
            raise FileNotFoundError(f"kapture {kind} {features!r} of image {image_name!r} not found: {path}")
        arrays[kind] = feature_files.read_feature_array(path, config)
    keypoints, descriptors = arrays["keypoints"], arrays["descriptors"]
    if len(keypoints) != len(descriptors):
        raise ValueError(
            f"image {image_name!r} in {root}: {len(keypoints)} keypoints but {len(descriptors)} descriptors"
        )
    xy = keypoints[:, :2].astype(np.float64) + settings.pixel_offset
    return {"keypoints": xy.astype(np.float32), "descriptors": descriptors}
