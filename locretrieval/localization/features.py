"""Local features of an image set, cached on disk: SIFT through pycolmap, or kapture files.

Keypoints are ``float32 [n, 2]`` pixel coordinates in the full-resolution image, in COLMAP's
convention (the centre of the first pixel is (0.5, 0.5)), the convention of `Camera`.
Descriptors are ``[n, D]`` as produced (pycolmap: uint8 RootSIFT scaled by 512; kapture:
the stored dtype).

The ``features`` config picks a ``type`` and reads that type's section:

- ``sift``: ``max_side`` (px; images whose longer side exceeds it are downscaled for
  extraction, keypoints scaled back), ``first_octave``, ``max_num_features``,
  ``peak_threshold`` (pycolmap's SIFT options);
- ``kapture``: precomputed features of the kapture folder each image comes from
  (``reconstruction/keypoints/<name>/<image>.kpt`` and ``descriptors/<name>/<image>.desc``
  with their ``keypoints.txt``/``descriptors.txt`` headers, e.g. the published R2D2
  features); ``pixel_offset`` is added to their x and y (0.5 converts keypoints whose first
  pixel centre is (0, 0), as R2D2 and OpenCV write them, to COLMAP's convention).

Features live in ``<cache_dir>/features/<image set fingerprint>-<config key>/`` as HDF5
shards (`ShardedStore`) keyed by image name, computed once and reused across runs.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import kapture
import kapture.io.csv as kapture_csv
import kapture.io.features as kapture_features
import numpy as np
from PIL import Image

from locretrieval.cache import config_key
from locretrieval.localization.store import ShardedStore
from locretrieval.localization.workers import parallel_map
from locretrieval.scene import ImageSet
from locretrieval.scene.feature_files import read_feature_array, read_feature_header
from locretrieval.scene.images import read_image

log = logging.getLogger(__name__)

FEATURE_TYPES = ("sift", "kapture")
DEFAULT_FEATURES: dict[str, Any] = {
    "type": "sift",
    "sift": {"max_side": 640, "first_octave": 0, "max_num_features": 4096, "peak_threshold": 0.0066667},
    "kapture": {"name": "r2d2", "pixel_offset": 0.5},
}
SIFT_DIMENSION = 128
#: Images per shard (one task of a worker).
IMAGES_PER_SHARD = 32
#: Bump when the meaning of cached features changes.
CACHE_VERSION = 1


def feature_settings(config: Mapping[str, Any] | None) -> dict[str, Any]:
    """``{"type": ..., <type>: {...}}``: the settings that determine the features (defaults filled in)."""
    config = dict(config or {})
    kind = config.get("type", DEFAULT_FEATURES["type"])
    if kind not in FEATURE_TYPES:
        raise ValueError(f"unknown local feature type {kind!r}; expected one of {FEATURE_TYPES}")
    settings = {**DEFAULT_FEATURES[kind], **dict(config.get(kind) or {})}
    unknown = sorted(set(settings) - set(DEFAULT_FEATURES[kind]))
    if unknown:
        raise ValueError(f"unknown {kind} feature settings {unknown}; known: {sorted(DEFAULT_FEATURES[kind])}")
    return {"type": kind, kind: settings}


def feature_key(config: Mapping[str, Any] | None) -> str:
    """Cache key of a feature configuration (only the settings of the chosen type count)."""
    return config_key(CACHE_VERSION, feature_settings(config))


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


def extract_features(
    images: ImageSet, config: Mapping[str, Any] | None, cache_dir: str | Path, workers: int | None = 1
) -> FeatureStore:
    """The features of every image of ``images``, extracting (or reading) only missing ones."""
    settings = feature_settings(config)
    store = FeatureStore(Path(cache_dir) / "features" / f"{images.fingerprint(include_poses=False)}-{feature_key(config)}")
    paths = dict(zip(images.names, images.paths))
    missing = store.store.missing(images.names)
    if missing:
        log.info("local features (%s) of %d images into %s", settings["type"], len(missing), store.folder)
        chunks = [missing[start : start + IMAGES_PER_SHARD] for start in range(0, len(missing), IMAGES_PER_SHARD)]
        tasks = [[(name, str(paths[name])) for name in chunk] for chunk in chunks]
        shared = (str(store.folder), settings)
        for _ in parallel_map(_extract_shard, tasks, workers, f"features ({settings['type']})", shared):
            pass
        store.store.refresh()
    return store


def _extract_shard(shared: tuple[str, dict[str, Any]], images: list[tuple[str, str]]) -> int:
    """Worker: features of one chunk of ``(name, image path)``, written as one shard."""
    folder, settings = shared
    kind = settings["type"]
    if kind == "sift":
        extract = _sift_extractor(settings["sift"])
        records = {name: extract(Path(path)) for name, path in images}
    else:
        records = {name: _read_kapture_features(name, Path(path), settings["kapture"]) for name, path in images}
    ShardedStore(folder).write(records)
    return len(records)


def _sift_extractor(settings: Mapping[str, Any]):
    """``path -> {"keypoints", "descriptors"}`` with pycolmap's CPU SIFT."""
    import pycolmap

    options = pycolmap.FeatureExtractionOptions()
    options.num_threads = 1
    options.sift.first_octave = int(settings["first_octave"])
    options.sift.max_num_features = int(settings["max_num_features"])
    options.sift.peak_threshold = float(settings["peak_threshold"])
    extractor = pycolmap.FeatureExtractor.create(options)
    max_side = int(settings["max_side"])

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
        return {"keypoints": xy.astype(np.float32), "descriptors": np.asarray(descriptors.data, dtype=np.uint8).reshape(len(xy), SIFT_DIMENSION)}

    return extract


def kapture_root_of(image_path: Path, name: str) -> Path:
    """The kapture folder of an image at ``<kapture>/sensors/records_data/<name>``."""
    records_data = Path(str(image_path)[: -len(name)]) if str(image_path).endswith(name) else None
    if records_data is None or records_data.parts[-2:] != ("sensors", "records_data"):
        raise ValueError(f"image {image_path} is not inside a kapture folder's sensors/records_data/")
    return records_data.parent.parent


def _read_kapture_features(image_name: str, image_path: Path, settings: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Keypoints (x, y shifted by ``pixel_offset``) and descriptors of one image from kapture files."""
    root = str(kapture_root_of(image_path, image_name))
    features = settings["name"]
    arrays = {}
    for kind, header_type, full_path in (
        ("keypoints", kapture.Keypoints, kapture_features.get_keypoints_fullpath),
        ("descriptors", kapture.Descriptors, kapture_features.get_descriptors_fullpath),
    ):
        header = Path(kapture_csv.get_feature_csv_fullpath(header_type, features, root))
        if not header.is_file():
            raise FileNotFoundError(f"kapture {kind} {features!r} not found: {header} is missing")
        config = read_feature_header(header, kind)
        path = Path(full_path(features, root, image_name))
        if not path.is_file():
            raise FileNotFoundError(f"kapture {kind} {features!r} of image {image_name!r} not found: {path}")
        arrays[kind] = read_feature_array(path, config)
    keypoints, descriptors = arrays["keypoints"], arrays["descriptors"]
    if len(keypoints) != len(descriptors):
        raise ValueError(f"image {image_name!r} in {root}: {len(keypoints)} keypoints but {len(descriptors)} descriptors")
    xy = keypoints[:, :2].astype(np.float64) + float(settings["pixel_offset"])
    return {"keypoints": xy.astype(np.float32), "descriptors": descriptors}
