"""Global descriptors read from kapture global-features folders (e.g. those NAVER publishes) or
from hloc's global-features HDF5 files.

A folder (kapture >= 1.1 layout, ``<kapture>/reconstruction/global_features/<name>``, or the
downloader's ``<dataset>/global_features/<name>/global_features``) holds
``global_features.txt`` (``name, dtype, dsize, metric_type``) and one raw ``.gfeat`` file
per image at ``<folder>/<image name relative to records_data>.gfeat``. An hloc file
(``global-feats-netvlad.h5``) holds a ``global_descriptor`` dataset in the group of each image
name (`locretrieval.models.files.feature_io`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from locretrieval.cache import config_key, tree_signature
from locretrieval.config import folder_label
from locretrieval.models.base import NORM_TOLERANCE, GlobalDescriptor
from locretrieval.scene import ImageSet, Scene
from locretrieval.scene.feature_files import (
    FeatureHeader,
    feature_file,
    feature_folder_candidates,
    feature_names,
    find_feature_folder,
    read_feature_array,
    read_feature_header,
)

log = logging.getLogger(__name__)

KIND = "global_features"
CONFIG_FILENAME = f"{KIND}.txt"
#: Suffixes of hloc's feature files: a ``model.path`` ending so is read as one.
HLOC_SUFFIXES = (".h5", ".hdf5")


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
    """The global-feature folders of ``feature_name`` for the scene's kapture ``sources``, in
    kapture's layout (``<source>/reconstruction/global_features/<name>``) or the downloader's
    (``<dataset>/global_features/<name>/global_features``), each folder once.

    Without a ``feature_name``, the single feature type found for the sources is used.
    """
    if feature_name is None:
        names = sorted(set().union(*(feature_names(source, KIND) for source in sources)))
        if len(names) != 1:
            searched = sorted({str(c.parent) for s in sources for c in feature_folder_candidates(s, KIND, "*")})
            raise ValueError(
                f"model.feature_name is not set and the scene sources hold {len(names)} global-feature types "
                f"{names} (searched {searched}); set model.feature_name or model.path"
            )
        feature_name = names[0]
    found = [find_feature_folder(source, KIND, feature_name) for source in sources]
    folders = list(dict.fromkeys(folder for folder in found if folder is not None))
    if not folders:
        searched = [str(c) for s in sources for c in feature_folder_candidates(s, KIND, feature_name)]
        raise FileNotFoundError(f"no global features {feature_name!r}: searched {searched}")
    return folders


def as_folders(path: str | os.PathLike | Sequence[str | os.PathLike]) -> list[Path]:
    """``model.path``, one folder or a list, as a list of folders."""
    return [Path(path)] if isinstance(path, (str, os.PathLike)) else [Path(p) for p in path]


def missing_feature_folders(
    path: str | os.PathLike | Sequence[str | os.PathLike] | None, feature_name: str | None, sources: Sequence[Path]
) -> list[str]:
    """What the features of `PrecomputedDescriptor` lack: the header of each ``path`` folder, or
    (``path`` None) any folder of ``feature_name`` among the ``sources``."""
    if path is not None and is_hloc(as_folders(path)):
        return [f"hloc global features {file} not found" for file in as_folders(path) if not file.is_file()]
    if path is not None:
        headers = [folder / CONFIG_FILENAME for folder in as_folders(path)]
        return [f"global features {header} not found" for header in headers if not header.is_file()]
    try:
        find_feature_folders(sources, feature_name)
    except (FileNotFoundError, ValueError) as error:
        return [str(error)]
    return []


def is_hloc(paths: Sequence[Path]) -> bool:
    """Whether ``model.path`` names hloc files (`HLOC_SUFFIXES`), not kapture folders; both at once are refused."""
    hloc = [path.suffix.lower() in HLOC_SUFFIXES for path in paths]
    if any(hloc) and not all(hloc):
        raise ValueError(f"model.path mixes hloc files and kapture folders: {[str(path) for path in paths]}")
    return bool(hloc) and all(hloc)


class PrecomputedDescriptor(GlobalDescriptor):
    """Reads published global descriptors instead of computing them.

    ``path``: one folder or a list (e.g. the mapping's and the query's
    ``reconstruction/global_features/<name>``), or one hloc file or a list (`HLOC_SUFFIXES`, e.g.
    the database's and the queries'); each image is read from the first folder or file holding
    it. When ``path`` is ``None``, `bind_scene` finds the folders of
    ``feature_name`` for every ``Scene.sources`` entry (`find_feature_folders`: kapture's
    layout or the downloader's). Without ``name`` or ``feature_name``, the ranking is named after
    the folders (`folder_label`, e.g. ``AP-GeM-LM18``). Descriptors are converted to
    ``float32`` and L2-normalised (logged once per call when the files were not); rankings
    use the inner product, which orders unit vectors as the L2 metric does. The folders' headers
    are read when it is built; an absent one is named by `missing_inputs` (read once it is there).
    """

    def __init__(
        self,
        *,
        name: str | None,
        path: str | os.PathLike | Sequence[str | os.PathLike] | None,
        feature_name: str | None,
        allow_integer: bool,
    ) -> None:
        super().__init__(name or feature_name or "precomputed")
        self.allow_integer = bool(allow_integer)
        self._named = name is not None or feature_name is not None
        self.feature_name = feature_name
        self._folders: list[Path] | None = None
        self._paths = None if path is None else as_folders(path)
        self._hloc_files = self._paths if self._paths is not None and is_hloc(self._paths) else None
        if self._paths is not None:
            if not self._paths:
                raise ValueError("model.path is an empty list; give at least one global-features folder")
            if not self._named:
                self.name = folder_label(self._paths)
            if self._hloc_files is None and all((folder / CONFIG_FILENAME).is_file() for folder in self._paths):
                self._set_folders(self._paths)

    def missing_inputs(self, scene: Scene) -> list[str]:
        """The feature folders' headers that are absent (``path``), or why no folder of
        ``feature_name`` is among ``scene``'s sources."""
        key = "path" if self._paths is not None else "feature_name"
        problems = missing_feature_folders(self._paths, self.feature_name, scene.sources)
        return [f"{key}: {problem}" for problem in problems]

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
            self.name = folder_label(folders)

    @property
    def folders(self) -> list[Path]:
        if self._folders is None and self._paths is not None:
            self._set_folders(self._paths)  # absent when the model was built
        if self._folders is None:
            raise RuntimeError(
                "precomputed model has no feature folders: set model.path, or describe through "
                "describe_scene, which searches the scene's sources"
            )
        return self._folders

    def bind_scene(self, scene: Scene) -> None:
        """Find the feature folders under ``scene.sources`` unless ``path`` was given."""
        if self._paths is None:
            self._set_folders(find_feature_folders(scene.sources, self.feature_name))

    def identity(self) -> dict[str, Any]:
        if self._hloc_files is not None:
            files = self._hloc_files
            signature = config_key([tree_signature(file) for file in files])
            return {
                "model": "precomputed",
                "hloc_files": [str(file.resolve()) for file in files],
                "signature": signature,
            }
        folders = [str(folder.resolve()) for folder in self.folders]
        # The files' names, sizes and times, hashed: the key changes when a feature file does.
        signature = config_key([tree_signature(folder) for folder in self.folders])
        return {"model": "precomputed", "folders": folders, "signature": signature}

    @staticmethod
    def _feature_path(image_name: str, folders: list[Path]) -> Path:
        for folder in folders:
            candidate = feature_file(folder, KIND, image_name)
            if candidate.is_file():
                return candidate
        raise FileNotFoundError(
            f"no global feature for image {image_name!r}: searched {[str(folder) for folder in folders]}"
        )

    def describe(self, images: ImageSet) -> np.ndarray:
        if self._hloc_files is not None:
            from locretrieval.models.files.feature_io import read_hloc_global_descriptors  # h5py: for hloc files only

            files = ", ".join(str(file) for file in self._hloc_files)
            descriptors = read_hloc_global_descriptors(self._hloc_files, images.names)
            return self._unit_rows(descriptors, images.names, lambda name: f"{files}: image {name!r}")
        folders = self.folders
        header = self._config
        descriptors = np.empty((len(images), header.dsize), dtype=np.float32)
        for row, image_name in enumerate(images.names):
            path = self._feature_path(image_name, folders)
            actual_bytes, expected_bytes = path.stat().st_size, header.dsize * header.dtype.itemsize
            if actual_bytes != expected_bytes:
                raise ValueError(
                    f"{path}: {actual_bytes} bytes, expected {expected_bytes} ({header.dsize} x {header.dtype})"
                )
            descriptors[row] = read_feature_array(path, header).reshape(-1)
        return self._unit_rows(descriptors, images.names, lambda name: str(self._feature_path(name, folders)))

    def _unit_rows(self, descriptors: np.ndarray, names: Sequence[str], where: Callable[[str], str]) -> np.ndarray:
        """``descriptors`` (``float32``, a row per image of ``names``) L2-normalised; a row that is not
        finite or is all zeros is an error naming ``where(image name)``."""
        finite = np.isfinite(descriptors).all(axis=1)
        if not finite.all():
            raise ValueError(f"{where(names[int(np.argmin(finite))])}: global feature holds non-finite values")
        norms = np.linalg.norm(descriptors, axis=1)
        if len(norms) and not norms.all():
            raise ValueError(f"{where(names[int(np.argmin(norms))])}: global feature is all zeros")
        off = np.abs(norms - 1.0) > NORM_TOLERANCE
        if off.any():
            log.info(
                "%s: %d of %d global features were not L2-normalised (norms %.4g..%.4g); normalising",
                self.name,
                int(off.sum()),
                len(norms),
                norms.min(),
                norms.max(),
            )
        return descriptors / norms[:, None]
