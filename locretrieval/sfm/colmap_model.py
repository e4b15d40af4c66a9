"""Existing COLMAP models as `SparseMap`s; the conversions to pycolmap objects are
`locretrieval.scene.colmap`'s (imported here for the SfM modules)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from locretrieval.scene.colmap import (  # noqa: F401  (the SfM modules' conversions)
    MODEL_FILES,
    from_rigid3d,
    missing_model_files,
    to_pycolmap_camera,
    to_rigid3d,
)
from locretrieval.sfm.sparse_map import SparseMap

#: Largest distance (px) between a model's 2D point and the feature keypoint of the same index.
KEYPOINT_TOLERANCE = 0.01


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
