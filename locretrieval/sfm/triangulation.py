"""The triangulate stage of the SfM pipeline: sparse maps from images with known poses.

A triangulation is an object chosen by ``_target_`` (``sfm/triangulation=colmap|batched``), a
`Triangulation` that turns maps to build (`MapInput`: images with cameras, fixed world-to-camera
poses and keypoints, and the verified matches of their pairs) into `SparseMap`s, many at once:

- `ColmapTriangulation` (the default, as the reference tools triangulate): per map, a pycolmap
  ``Reconstruction`` holding the images and keypoints, a ``CorrespondenceGraph`` of the matches,
  and ``IncrementalTriangulator`` over every image (tracks formed through the correspondence
  graph, RANSAC per track), then tracks completed and merged and points filtered by
  reprojection error and triangulation angle (`triangulate_known_poses`);
- `BatchedTriangulation`: every map of the call in one vectorised pass: tracks are the connected
  keypoints of the match graph (an image seen twice in a track leaves it), each track's point is
  the linear (DLT) solution of its observations; twice, each track's worst observation is dropped
  when it is beyond the reprojection error and the points solved again; then every observation
  beyond it is dropped, and points under the triangulation angle or seen by fewer than 2 images.
  No RANSAC, merging or completion: several times faster than COLMAP,
  with maps of the same kind (docs/performance.md measures both).

Poses are never changed.
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.config import require
from locretrieval.scene import Camera
from locretrieval.sfm.colmap_model import to_pycolmap_camera, to_rigid3d
from locretrieval.sfm.sparse_map import SparseMap

if TYPE_CHECKING:
    import pycolmap  # imported where it is used: a run without SfM does not load it


@dataclass(frozen=True)
class MapInput:
    """One map to triangulate: image ``i`` has ``cameras[i]``, the world-to-camera pose
    ``qvec[i]`` (wxyz) / ``tvec[i]`` and ``keypoints[i] [n_i, 2]`` (COLMAP's pixel convention);
    ``matches[(i, j)] [m, 2]``: verified keypoint indices of image i and image j (i < j)."""

    cameras: Sequence[Camera]
    qvec: np.ndarray
    tvec: np.ndarray
    keypoints: Sequence[np.ndarray]
    matches: Mapping[tuple[int, int], np.ndarray]


class Triangulation(abc.ABC):
    """Points of maps of images with known poses: ``min_angle`` (degrees) smallest triangulation
    angle of a point; observations beyond ``max_reprojection_error`` px are dropped (and points
    left with fewer than 2 images)."""

    min_angle: float
    max_reprojection_error: float

    @abc.abstractmethod
    def triangulate_many(self, maps: Sequence[MapInput]) -> list[SparseMap]:
        """The map of each input, in order."""

    def triangulate(
        self,
        cameras: Sequence[Camera],
        qvec: np.ndarray,
        tvec: np.ndarray,
        keypoints: Sequence[np.ndarray],
        matches: Mapping[tuple[int, int], np.ndarray],
    ) -> SparseMap:
        """One map (`MapInput`'s arguments)."""
        return self.triangulate_many([MapInput(cameras, qvec, tvec, keypoints, matches)])[0]

    def identity(self) -> dict:
        """What determines the maps (part of their cache keys)."""
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    def _check(self) -> None:
        require(self.min_angle >= 0, "min_angle", f"must be >= 0 degrees, got {self.min_angle}")
        require(
            self.max_reprojection_error > 0,
            "max_reprojection_error",
            f"must be a positive number of pixels, got {self.max_reprojection_error}",
        )


@dataclass
class ColmapTriangulation(Triangulation):
    """COLMAP's point triangulator with fixed poses (`triangulate_known_poses`), one map at a time;
    ``ignore_two_view_tracks`` (COLMAP's default True halves the points of small maps);
    ``random_seed`` of its RANSAC (deterministic maps)."""

    min_angle: float
    max_reprojection_error: float
    ignore_two_view_tracks: bool
    random_seed: int

    def __post_init__(self) -> None:
        self._check()

    def triangulate_many(self, maps: Sequence[MapInput]) -> list[SparseMap]:
        return [triangulate_known_poses(m.cameras, m.qvec, m.tvec, m.keypoints, m.matches, self) for m in maps]


#: Matches of the maps triangulated in one vectorised pass of `BatchedTriangulation`.
BATCH_MATCHES = 100_000
#: Passes of `BatchedTriangulation` that each drop every track's worst observation beyond the error.
OUTLIER_PASSES = 2


@dataclass
class BatchedTriangulation(Triangulation):
    """Every map of a call in one vectorised pass (linear triangulation of the match graph's tracks)."""

    min_angle: float
    max_reprojection_error: float

    def __post_init__(self) -> None:
        self._check()

    def identity(self) -> dict:
        return {"batched": dataclasses.asdict(self)}

    def triangulate_many(self, maps: Sequence[MapInput]) -> list[SparseMap]:
        """The maps in vectorised passes of about `BATCH_MATCHES` matches each (a working set
        that stays in the CPU's caches: larger passes are slower per map)."""
        result: list[SparseMap] = []
        batch: list[MapInput] = []
        for index, map_input in enumerate(maps):
            batch.append(map_input)
            if index + 1 == len(maps) or sum(len(m) for b in batch for m in b.matches.values()) >= BATCH_MATCHES:
                result += batched_triangulation(batch, self.min_angle, self.max_reprojection_error)
                batch = []
        return result


def triangulate_known_poses(
    cameras: Sequence[Camera],
    qvec: np.ndarray,
    tvec: np.ndarray,
    keypoints: Sequence[np.ndarray],
    matches: Mapping[tuple[int, int], np.ndarray],
    settings: ColmapTriangulation,
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
            name=str(index),
            keypoints=np.asarray(image_keypoints, dtype=np.float64).reshape(-1, 2),
            camera_id=image_id,
            image_id=image_id,
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
            observed_ids = np.fromiter(
                (p.point3D_id for p in image.get_observation_points2D()), dtype=np.int64, count=len(observed)
            )
            ids[observed] = np.searchsorted(point_ids, observed_ids)
        observations.append(ids)
    return SparseMap(points, observations)


def batched_triangulation(maps: Sequence[MapInput], min_angle: float, max_error: float) -> list[SparseMap]:
    """`BatchedTriangulation` of ``maps``. Every image of every map is a "view" with its offset in
    one joint keypoint numbering, every match an edge between two keypoints; the tracks are the
    connected components. A map's numbers are relative to its mean camera centre (well-conditioned
    normal equations in any world frame), so its points do not depend on the other maps of the call."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    views = [(m, i) for m, map_input in enumerate(maps) for i in range(len(map_input.cameras))]
    first_node = np.concatenate([[0], np.cumsum([len(maps[m].keypoints[i]) for m, i in views])]).astype(np.int64)
    view_of = {view: v for v, view in enumerate(views)}
    ends = [
        (
            first_node[view_of[(m, a)]] + np.asarray(matches[:, 0], dtype=np.int64),
            first_node[view_of[(m, b)]] + np.asarray(matches[:, 1], dtype=np.int64),
        )
        for m, map_input in enumerate(maps)
        for (a, b), matches in map_input.matches.items()
        if len(matches)
    ]
    empty = [
        SparseMap(np.empty((0, 3)), [np.full(len(k), -1, dtype=np.int64) for k in map_input.keypoints])
        for map_input in maps
    ]
    if not ends:
        return empty
    nodes, index = np.unique(
        np.concatenate([np.concatenate([e[0] for e in ends]), np.concatenate([e[1] for e in ends])]),
        return_inverse=True,
    )
    half = len(index) // 2
    _, track = connected_components(
        coo_matrix((np.ones(half), (index[:half], index[half:])), shape=(len(nodes), len(nodes))), directed=False
    )
    view = np.searchsorted(first_node, nodes, side="right") - 1
    # observations sorted by track (segments); an image seen twice in one track leaves it
    order = np.lexsort((view, track))
    track, view, keypoint = track[order], view[order], (nodes - first_node[view])[order]
    twice = np.zeros(len(track), dtype=bool)
    twice[1:] = (track[1:] == track[:-1]) & (view[1:] == view[:-1])
    twice[:-1] |= twice[1:]
    track, view, keypoint = track[~twice], view[~twice], keypoint[~twice]
    geometry_ = _ViewGeometry(maps, views, view, keypoint)
    for final in [False] * OUTLIER_PASSES + [True]:
        points = geometry_.points(track)
        error = geometry_.reprojection_errors(points, track)
        if final:  # every observation beyond the error leaves (NaN: behind the camera, or unsolved), and lone ones
            inlier = error <= max_error
            inlier &= _segment_counts(track[inlier], len(points))[track] >= 2
        else:  # each track's worst observation leaves when it is beyond the error; then solved again
            inlier = ~_worst_beyond(track, np.nan_to_num(error, nan=np.inf), max_error)
        track, view, keypoint = track[inlier], view[inlier], keypoint[inlier]
        geometry_ = geometry_.subset(inlier)
    points = geometry_.points(track)
    kept = (_segment_counts(track, len(points)) >= 2) & (
        _max_angles(track, view, points, geometry_.centers, len(points)) >= min_angle
    )
    inlier = kept[track]
    return _sparse_maps(
        maps,
        views,
        points + geometry_.track_origins(track, len(points)),
        track[inlier],
        view[inlier],
        keypoint[inlier],
        empty,
    )


class _ViewGeometry:
    """The views' poses relative to their map's origin (the mean camera centre: ``R``, ``t``,
    ``centers``, ``origins`` per view), and per observation its undistorted normalised ray
    ``rays [o, 2]`` and its camera's mean focal length ``focal [o]`` (px)."""

    def __init__(self, maps: Sequence[MapInput], views, view: np.ndarray, keypoint: np.ndarray) -> None:
        from locretrieval import geometry
        from locretrieval.sfm.colmap_model import to_pycolmap_camera

        if maps is None:  # `subset`
            return
        self.R = np.stack([geometry.quaternion_to_matrix(maps[m].qvec[i]) for m, i in views])
        t = np.stack([np.asarray(maps[m].tvec[i], dtype=np.float64) for m, i in views])
        centers = -np.einsum("vji,vj->vi", self.R, t)
        map_of_view = np.array([m for m, _ in views])
        self.origins = np.stack([centers[map_of_view == m].mean(axis=0) for m in range(len(maps))])[map_of_view]
        self.t = t + np.einsum("vij,vj->vi", self.R, self.origins)
        self.centers = centers - self.origins
        self.rays, self.focal = np.empty((len(view), 2)), np.empty(len(view))
        self.view = view
        self.R_obs, self.t_obs = self.R[view], self.t[view]  # per observation, gathered once
        for v in np.unique(view):
            m, i = views[v]
            rows = np.flatnonzero(view == v)
            camera = to_pycolmap_camera(maps[m].cameras[i])
            self.rays[rows] = camera.cam_from_img(
                np.asarray(maps[m].keypoints[i], dtype=np.float64)[keypoint[rows]]
            ).reshape(-1, 2)
            self.focal[rows] = camera.mean_focal_length()

    def subset(self, rows: np.ndarray) -> "_ViewGeometry":
        kept = _ViewGeometry(None, None, None, None)  # type: ignore[arg-type]
        kept.R, kept.t, kept.centers, kept.origins = self.R, self.t, self.centers, self.origins
        kept.rays, kept.focal, kept.view = self.rays[rows], self.focal[rows], self.view[rows]
        kept.R_obs, kept.t_obs = self.R_obs[rows], self.t_obs[rows]
        return kept

    def points(self, track: np.ndarray) -> np.ndarray:
        """Each track's point ``[T, 3]`` (relative to its map's origin): the least-squares solution
        of ``(x R3 - R1) X = -(x t3 - t1)`` and ``(y R3 - R2) X = -(y t3 - t2)`` over its
        observations (3 x 3 normal equations per track, solved in closed form); NaN with fewer
        than 2 observations or a singular system."""
        R, t = self.R_obs, self.t_obs
        x, y = self.rays[:, :1], self.rays[:, 1:]
        rows = (x * R[:, 2] - R[:, 0], y * R[:, 2] - R[:, 1])
        sides = (-(x[:, 0] * t[:, 2] - t[:, 0]), -(y[:, 0] * t[:, 2] - t[:, 1]))
        count = track.max(initial=-1) + 1
        starts = _segment_starts(track)
        normal = np.empty((len(starts), 3, 3))
        target = np.empty((len(starts), 3))
        for a in range(3):
            target[:, a] = (
                np.add.reduceat(rows[0][:, a] * sides[0] + rows[1][:, a] * sides[1], starts) if len(starts) else 0
            )
            for b in range(a, 3):
                normal[:, a, b] = normal[:, b, a] = (
                    np.add.reduceat(rows[0][:, a] * rows[0][:, b] + rows[1][:, a] * rows[1][:, b], starts)
                    if len(starts)
                    else 0
                )
        solved = np.full((count, 3), np.nan)
        if len(starts):
            with np.errstate(divide="ignore", invalid="ignore"):
                adjugate = np.cross(
                    normal[:, [1, 2, 0]], normal[:, [2, 0, 1]], axis=2
                )  # rows: cofactors of a symmetric matrix
                determinant = np.einsum("ti,ti->t", normal[:, 0], adjugate[:, 0])
                values = np.einsum("tij,tj->ti", adjugate, target) / determinant[:, None]
            values[np.abs(determinant) < 1e-12 * np.abs(normal).max(axis=(1, 2)) ** 3] = np.nan
            solved[track[starts]] = values
        solved[_segment_counts(track, count) < 2] = np.nan
        return solved

    def reprojection_errors(self, points: np.ndarray, track: np.ndarray) -> np.ndarray:
        """Per observation, the distance (px, through the mean focal length) between its ray and
        its point's projection; NaN behind the camera or for an unsolved point."""
        in_camera = np.einsum("oij,oj->oi", self.R_obs, points[track]) + self.t_obs
        with np.errstate(divide="ignore", invalid="ignore"):
            error = np.linalg.norm(in_camera[:, :2] / in_camera[:, 2:] - self.rays, axis=1) * self.focal
        return np.where(in_camera[:, 2] > 0, error, np.nan)

    def track_origins(self, track: np.ndarray, count: int) -> np.ndarray:
        """Each track's map origin ``[T, 3]`` (zero for tracks without an observation)."""
        origins = np.zeros((count, 3))
        origins[track] = self.origins[self.view]
        return origins


def _worst_beyond(track: np.ndarray, error: np.ndarray, max_error: float) -> np.ndarray:
    """Boolean per observation: its track's largest error (the first, on a tie), when above ``max_error``."""
    starts = _segment_starts(track)
    chosen = np.zeros(len(track), dtype=bool)
    if len(starts):
        chosen[_first_of_segments(track, error >= np.maximum.reduceat(error, starts)[_segments(track)])] = True
    return chosen & (error > max_error)


def _segments(track: np.ndarray) -> np.ndarray:
    """The index of each observation's run in the sorted ``track``."""
    return np.cumsum(np.r_[False, track[1:] != track[:-1]]) if len(track) else track


def _first_of_segments(track: np.ndarray, candidate: np.ndarray) -> np.ndarray:
    """Per run of the sorted ``track``, the first observation where ``candidate`` holds (each run must hold one)."""
    rows = np.flatnonzero(candidate)
    runs = _segments(track)[rows]
    return rows[np.r_[True, runs[1:] != runs[:-1]]]


def _segment_starts(track: np.ndarray) -> np.ndarray:
    """Where each run of equal values of the sorted ``track`` starts."""
    return np.flatnonzero(np.r_[True, track[1:] != track[:-1]]) if len(track) else np.empty(0, dtype=np.int64)


def _segment_counts(track: np.ndarray, count: int) -> np.ndarray:
    return np.bincount(track, minlength=count)


def _max_angles(track: np.ndarray, view: np.ndarray, points: np.ndarray, centers: np.ndarray, count: int) -> np.ndarray:
    """Each track's largest angle (degrees) between two of its viewing rays, found as the angle
    between the ray furthest from the track's first ray and the ray furthest from that one."""
    directions = points[track] - centers[view]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    starts = _segment_starts(track)
    angles = np.zeros(count)
    if not len(starts):
        return angles
    extreme = _furthest(track, directions, directions[starts], starts)
    opposite = _furthest(track, directions, directions[extreme], starts)
    cosine = np.einsum("ti,ti->t", directions[extreme], directions[opposite])
    angles[track[starts]] = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    return angles


def _furthest(track: np.ndarray, directions: np.ndarray, reference: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Per track segment, the observation whose direction makes the largest angle with the
    segment's ``reference`` direction."""
    segment = _segments(track)
    cosine = np.nan_to_num(np.einsum("oi,oi->o", directions, reference[segment]), nan=2.0)
    return _first_of_segments(track, cosine <= np.minimum.reduceat(cosine, starts)[segment])


def _sparse_maps(maps, views, points, track, view, keypoint, empty) -> list[SparseMap]:
    """The kept observations and their points, as one `SparseMap` per map (points renumbered)."""
    result = list(empty)
    map_of_view = np.array([m for m, _ in views])
    for m in range(len(maps)):
        mine = map_of_view[view] == m
        rows, renumbered = np.unique(track[mine], return_inverse=True)
        observations = [np.full(len(k), -1, dtype=np.int64) for k in maps[m].keypoints]
        for v in np.unique(view[mine]):
            at = view[mine] == v
            observations[views[v][1]][keypoint[mine][at]] = renumbered[at]
        result[m] = SparseMap(points[rows], observations)
    return result
