"""Global descriptors read from kapture global-features folders (e.g. those NAVER publishes).

A folder (kapture >= 1.1 layout, ``<kapture>/reconstruction/global_features/<name>``) holds
``global_features.txt`` (``name, dtype, dsize, metric_type``) and one raw ``.gfeat`` file
per image at ``<folder>/<image name relative to records_data>.gfeat``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import kapture
import kapture.io.features
import numpy as np

from locretrieval.cache import config_key, tree_signature
from locretrieval.models.base import NORM_TOLERANCE, GlobalDescriptor
from locretrieval.scene import ImageSet, Scene
from locretrieval.scene.feature_files import FeatureHeader, read_feature_array, read_feature_header

log = logging.getLogger(__name__)

CONFIG_FILENAME = "global_features.txt"
FEATURE_EXTENSION = kapture.io.features.FEATURE_FILE_EXTENSION[kapture.GlobalFeatures]
#: Where kapture keeps global features inside a kapture folder.
FEATURES_SUBDIR = Path(kapture.io.features.FEATURES_DATA_DIRNAMES[kapture.GlobalFeatures])


def read_config(folder: Path, allow_integer: bool = False) -> FeatureHeader:
    """The ``(name, dtype, dsize, metric_type)`` header of a global-features folder.

    Global descriptors are floating point: an integer dtype (whose bytes would be read as
    garbage if the files actually hold floats) is an error unless ``allow_integer``.
    """
    header = read_feature_header(folder / CONFIG_FILENAME, "global_features")
    if header.dtype.kind != "f" and not allow_integer:
        raise ValueError(
            f"{header.path}: dtype {header.dtype} is not floating point; global descriptors are float16/32/64. "
            "If the files really hold integer descriptors, set model.allow_integer=true"
        )
    return header


def find_feature_folders(sources: Sequence[Path], feature_name: str | None) -> list[Path]:
    """``<source>/reconstruction/global_features/<feature_name>`` folders that exist.

    Without a ``feature_name``, the single feature type found under the sources is used.
    """
    roots = [Path(source) / FEATURES_SUBDIR for source in sources]
    if feature_name is None:
        present = [child for root in roots if root.is_dir() for child in root.iterdir()]
        names = sorted({child.name for child in present if (child / CONFIG_FILENAME).is_file()})
        if len(names) != 1:
            raise ValueError(
                f"model.feature_name is not set and the scene sources hold {len(names)} global-feature types "
                f"{names} under {[str(root) for root in roots]}; set model.feature_name or model.path"
            )
        feature_name = names[0]
    folders = [root / feature_name for root in roots if (root / feature_name / CONFIG_FILENAME).is_file()]
    if not folders:
        raise FileNotFoundError(
            f"no global features {feature_name!r}: searched {[str(root / feature_name) for root in roots]}"
        )
    return folders


class PrecomputedDescriptor(GlobalDescriptor):
    """Reads published global descriptors instead of computing them.

    ``path``: one folder or a list (e.g. the mapping's and the query's
    ``reconstruction/global_features/<name>``); each image is read from the first folder
    holding its file. When ``path`` is ``None``, `bind_scene` searches
    ``<source>/reconstruction/global_features/<feature_name>`` under every
    ``Scene.sources`` entry. Descriptors are converted to ``float32`` and L2-normalised
    (logged once per call when the files were not); rankings use the inner product,
    which orders unit vectors as the L2 metric does.
    """

    def __init__(
        self,
        name: str | None = None,
        path: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
        feature_name: str | None = None,
        allow_integer: bool = False,
    ) -> None:
        super().__init__(name or feature_name or "precomputed")
        self.allow_integer = bool(allow_integer)
        self._named = name is not None or feature_name is not None
        self.feature_name = feature_name
        self._folders: list[Path] | None = None
        self._from_sources = path is None
        if path is not None:
            paths = [path] if isinstance(path, (str, os.PathLike)) else list(path)
            if not paths:
                raise ValueError("model.path is an empty list; give at least one global-features folder")
            self._set_folders([Path(p) for p in paths])

    def _set_folders(self, folders: list[Path]) -> None:
        configs = [read_config(folder, self.allow_integer) for folder in folders]
        for folder, config in zip(folders[1:], configs[1:]):
            first, other = (configs[0].dsize, configs[0].dtype), (config.dsize, config.dtype)
            if other != first:
                raise ValueError(
                    f"inconsistent global features: {folders[0]} holds {first[0]} x {first[1]}, "
                    f"{folder} holds {other[0]} x {other[1]}"
                )
        if str(configs[0].metric_type).upper() != "L2":
            log.warning(
                "global features %s declare metric %r; ranking uses cosine similarity",
                folders[0],
                configs[0].metric_type,
            )
        self._folders = folders
        self._config = configs[0]
        if not self._named:
            self.name = configs[0].name

    @property
    def folders(self) -> list[Path]:
        if self._folders is None:
            raise RuntimeError(
                "precomputed model has no feature folders: set model.path, or describe through "
                "describe_scene, which searches the scene's sources"
            )
        return self._folders

    def bind_scene(self, scene: Scene) -> None:
        """Find the feature folders under ``scene.sources`` unless ``path`` was given."""
        if self._from_sources:
            self._set_folders(find_feature_folders(scene.sources, self.feature_name))

    def identity(self) -> dict[str, Any]:
        folders = [str(folder.resolve()) for folder in self.folders]
        # The files' names, sizes and times, hashed: the key changes when a feature file does.
        signature = config_key([tree_signature(folder) for folder in self.folders])
        return {"model": "precomputed", "folders": folders, "signature": signature}

    @staticmethod
    def _feature_path(image_name: str, folders: list[Path]) -> Path:
        for folder in folders:
            candidate = folder / f"{image_name}{FEATURE_EXTENSION}"
            if candidate.is_file():
                return candidate
        raise FileNotFoundError(
            f"no global feature for image {image_name!r}: searched {[str(folder) for folder in folders]}"
        )

    def describe(self, images: ImageSet) -> np.ndarray:
        folders = self.folders
        header = self._config
        descriptors = np.empty((len(images), header.dsize), dtype=np.float32)
        for row, image_name in enumerate(images.names):
            path = self._feature_path(image_name, folders)
            actual_bytes, expected_bytes = path.stat().st_size, header.dsize * header.dtype.itemsize
            if actual_bytes != expected_bytes:
                raise ValueError(f"{path}: {actual_bytes} bytes, expected {expected_bytes} ({header.dsize} x {header.dtype})")
            vector = read_feature_array(path, header)
            if not np.isfinite(vector).all():
                raise ValueError(f"{path}: global feature holds non-finite values")
            descriptors[row] = vector.reshape(-1)
        norms = np.linalg.norm(descriptors, axis=1)
        if len(norms) and not norms.all():
            zero = self._feature_path(images.names[int(np.argmin(norms))], folders)
            raise ValueError(f"{zero}: global feature is all zeros")
        off = np.abs(norms - 1.0) > NORM_TOLERANCE
        if off.any():
            log.info(
                "%s: %d of %d global features were not L2-normalised (norms %.4g..%.4g); normalising",
                self.name, int(off.sum()), len(norms), norms.min(), norms.max(),
            )
        return descriptors / norms[:, None]
