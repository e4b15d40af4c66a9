"""Sparse maps triangulated from images with known poses (COLMAP's point triangulator, in memory).

`triangulate_known_poses` builds a pycolmap ``Reconstruction`` holding the images with their
fixed world-to-camera poses and keypoints, a ``CorrespondenceGraph`` of the verified pairwise
matches, and runs ``IncrementalTriangulator`` over every image (tracks are formed through
the correspondence graph, across all images), then completes and merges tracks and filters
points by reprojection error and triangulation angle. Poses are never changed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.config import require
from locretrieval.localization.colmap_model import to_pycolmap_camera, to_rigid3d
from locretrieval.localization.sparse_map import SparseMap
from locretrieval.scene import Camera

if TYPE_CHECKING:
    import pycolmap  # imported where it is used: a run without SfM does not load it


@dataclass
class TriangulationSettings:
    """COLMAP's point triangulator with fixed poses: ``min_angle`` (degrees) smallest triangulation
    angle; observations beyond ``max_reprojection_error`` px are dropped (and points left with
    fewer than 2); ``ignore_two_view_tracks`` (COLMAP's default True halves the points of small
    maps); ``random_seed`` of its RANSAC (deterministic maps)."""

    min_angle: float
    max_reprojection_error: float
    ignore_two_view_tracks: bool
    random_seed: int

    def __post_init__(self) -> None:
        require(self.min_angle >= 0, "min_angle", f"must be >= 0 degrees, got {self.min_angle}")
        require(self.max_reprojection_error > 0, "max_reprojection_error",
                f"must be a positive number of pixels, got {self.max_reprojection_error}")


def triangulate_known_poses(
    cameras: Sequence[Camera],
    qvec: np.ndarray,
    tvec: np.ndarray,
    keypoints: Sequence[np.ndarray],
    matches: Mapping[tuple[int, int], np.ndarray],
    settings: TriangulationSettings,
) -> SparseMap:
    """Triangulate the images ``i`` (camera, world-to-camera pose ``qvec[i]`` wxyz / ``tvec[i]``,
    keypoints ``[n_i, 2]`` in COLMAP's pixel convention) from verified ``matches[(i, j)]``
    (``[m, 2]`` keypoint indices of image i, image j)."""
    import pycolmap

    reconstruction = pycolmap.Reconstruction()
    graph = pycolmap.CorrespondenceGraph()
    for index, (camera, image_keypoints) in enumerate(zip(cameras, keypoints)):
        image_id = index + 1
        reconstruction.add_camera_with_trivial_rig(to_pycolmap_camera(camera, image_id))
        image = pycolmap.Image(
            name=str(index), keypoints=np.asarray(image_keypoints, dtype=np.float64).reshape(-1, 2),
            camera_id=image_id, image_id=image_id,
        )
        reconstruction.add_image_with_trivial_frame(image, to_rigid3d(qvec[index], tvec[index]))
        graph.add_image(image_id, len(image_keypoints))
    for (first, second), pair_matches in matches.items():
        if len(pair_matches):
            geometry = pycolmap.TwoViewGeometry()
            geometry.inlier_matches = np.asarray(pair_matches, dtype=np.uint32).reshape(-1, 2)
            graph.add_two_view_geometry(first + 1, second + 1, geometry)
    graph.finalize()

    options = pycolmap.IncrementalTriangulatorOptions()
    options.min_angle = settings.min_angle
    options.ignore_two_view_tracks = settings.ignore_two_view_tracks
    options.random_seed = settings.random_seed
    observation_manager = pycolmap.ObservationManager(reconstruction, graph)
    triangulator = pycolmap.IncrementalTriangulator(graph, reconstruction, observation_manager)
    for image_id in range(1, len(cameras) + 1):
        if graph.num_correspondences_for_image(image_id):
            triangulator.triangulate_image(options, image_id)
    triangulator.complete_all_tracks(options)
    triangulator.merge_all_tracks(options)
    observation_manager.filter_all_points3D(settings.max_reprojection_error, settings.min_angle)
    return _sparse_map(reconstruction, [len(k) for k in keypoints])


def _sparse_map(reconstruction: pycolmap.Reconstruction, num_keypoints: Sequence[int]) -> SparseMap:
    """The reconstruction's points (rows in ascending point id) and each image's observations,
    read per image (a loop over observations, not over every point's track in Python)."""
    point_ids = np.array(sorted(reconstruction.point3D_ids()), dtype=np.int64)
    points3D = reconstruction.points3D
    points = np.array([points3D[i].xyz for i in point_ids.tolist()], dtype=np.float64).reshape(-1, 3)
    observations = []
    for index, count in enumerate(num_keypoints):
        ids = np.full(count, -1, dtype=np.int64)
        image = reconstruction.images[index + 1]
        observed = np.asarray(image.get_observation_point2D_idxs(), dtype=np.int64)
        if len(observed):
            observed_ids = np.fromiter((p.point3D_id for p in image.get_observation_points2D()), dtype=np.int64, count=len(observed))
            ids[observed] = np.searchsorted(point_ids, observed_ids)
        observations.append(ids)
    return SparseMap(points, observations)
