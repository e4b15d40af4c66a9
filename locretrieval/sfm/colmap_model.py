"""Conversions to pycolmap objects, and existing COLMAP models as `SparseMap`s.

Poses cross this boundary as world-to-camera ``(q wxyz, t)`` on our side and
``Rigid3d(Rotation3d(xyzw), t)`` (``cam_from_world``) on pycolmap's. Cameras keep COLMAP's
model, parameters and pixel convention, so they are copied as they are.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.scene import Camera
from locretrieval.sfm.sparse_map import SparseMap

if TYPE_CHECKING:
    import pycolmap  # imported where it is used: a run without SfM does not load it

#: Largest distance (px) between a model's 2D point and the feature keypoint of the same index.
KEYPOINT_TOLERANCE = 0.01


def to_pycolmap_camera(camera: Camera, camera_id: int | None = None) -> pycolmap.Camera:
    """The same camera as a ``pycolmap.Camera`` (model, size and parameters copied)."""
    import pycolmap

    converted = pycolmap.Camera(
        model=camera.model, width=camera.width, height=camera.height, params=list(camera.params)
    )
    if camera_id is not None:
        converted.camera_id = camera_id
    return converted


def to_rigid3d(qvec: np.ndarray, tvec: np.ndarray) -> pycolmap.Rigid3d:
    """``cam_from_world`` of a world-to-camera pose (q wxyz, t)."""
    import pycolmap

    w, x, y, z = np.asarray(qvec, dtype=np.float64)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([x, y, z, w])), np.asarray(tvec, dtype=np.float64))


def from_rigid3d(cam_from_world: pycolmap.Rigid3d) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(q wxyz with w >= 0, t)`` of a pycolmap ``cam_from_world``."""
    x, y, z, w = cam_from_world.rotation.quat
    return geometry.normalize_quaternions(np.array([w, x, y, z])), np.asarray(
        cam_from_world.translation, dtype=np.float64
    )


#: The files of a COLMAP model folder, each ``<name>.bin`` or ``<name>.txt``.
MODEL_FILES = ("cameras", "images", "points3D")


def missing_model_files(folder: str | Path) -> list[str]:
    """What a COLMAP model ``folder`` lacks: the folder itself, or each of `MODEL_FILES`."""
    folder = Path(folder)
    if not folder.is_dir():
        return [f"COLMAP model folder {folder} not found"]
    return [
        f"{folder / name}.bin (or .txt) not found"
        for name in MODEL_FILES
        if not any((folder / f"{name}{suffix}").is_file() for suffix in (".bin", ".txt"))
    ]


def read_colmap_map(path: str | Path, names: Sequence[str], keypoints: Sequence[np.ndarray]) -> SparseMap:
    """The 3D points of a COLMAP model (text or binary folder) as a `SparseMap` over ``names``.

    The model's images are matched to ``names`` by name; each image's 2D points must be the
    feature ``keypoints`` of that image in the same order (a model triangulated from the
    same features, e.g. the published ``colmap-sfm`` maps with their R2D2 features), which
    is checked to ``KEYPOINT_TOLERANCE`` pixels. Images absent from the model observe nothing.
    """
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"COLMAP model folder not found: {path}")
    import pycolmap

    model = pycolmap.Reconstruction(path)
    by_name = {image.name: image for image in model.images.values()}
    missing = [name for name in names if name not in by_name]
    if len(missing) == len(names):
        raise ValueError(f"COLMAP model {path} has none of the {len(names)} database images (e.g. {names[0]!r})")
    point_ids = list(model.point3D_ids())
    row_of = {point_id: row for row, point_id in enumerate(point_ids)}
    points = np.array([model.points3D[i].xyz for i in point_ids], dtype=np.float64).reshape(-1, 3)
    observations = []
    for name, image_keypoints in zip(names, keypoints):
        ids = np.full(len(image_keypoints), -1, dtype=np.int64)
        image = by_name.get(name)
        if image is not None:
            xy = np.array([p.xy for p in image.points2D], dtype=np.float64).reshape(-1, 2)
            if len(xy) != len(image_keypoints) or (len(xy) and np.abs(xy - image_keypoints).max() > KEYPOINT_TOLERANCE):
                raise ValueError(
                    f"COLMAP model {path}, image {name!r}: its {len(xy)} 2D points are not the "
                    f"{len(image_keypoints)} feature keypoints; use the features the model was built from"
                )
            for index in image.get_observation_point2D_idxs():
                ids[index] = row_of[image.points2D[index].point3D_id]
        observations.append(ids)
    return SparseMap(points, observations)
