"""Kapture folders written by the kapture library: cameras, poses as kapture and 4x4 transforms, images."""

from __future__ import annotations

from pathlib import Path

import kapture
import kapture.io.csv as kapture_csv
import numpy as np
from PIL import Image

PINHOLE = kapture.Camera(kapture.CameraType.PINHOLE, [40, 30, 35.0, 36.0, 20.0, 15.0])
SIMPLE_RADIAL = kapture.Camera(kapture.CameraType.SIMPLE_RADIAL, [32, 24, 30.0, 16.0, 12.0, 0.01])


def rotation(axis: str, degrees: float) -> tuple[np.ndarray, list[float]]:
    """An explicit rotation matrix about a coordinate axis and its wxyz quaternion."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    matrices = {
        "x": [[1, 0, 0], [0, c, -s], [0, s, c]],
        "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
        "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]],
    }
    q = [np.cos(a / 2), 0.0, 0.0, 0.0]
    q["xyz".index(axis) + 1] = np.sin(a / 2)
    return np.array(matrices[axis], dtype=float), q


def transform(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def pose(axis: str, degrees: float, t) -> tuple[kapture.PoseTransform, np.ndarray]:
    """A kapture pose and the same transform as a 4x4 matrix."""
    R, q = rotation(axis, degrees)
    return kapture.PoseTransform(r=q, t=list(t)), transform(R, t)


def write_kapture(
    root: Path,
    sensors: dict[str, kapture.Sensor],
    records: dict[tuple[int, str], str],
    trajectories: dict[tuple[int, str], kapture.PoseTransform] | None = None,
    rigs: dict[tuple[str, str], kapture.PoseTransform] | None = None,
    depth: dict[tuple[int, str], str] | None = None,
) -> Path:
    """A kapture folder written by the kapture library, with PNG images of each camera's size."""
    data = kapture.Kapture(sensors=kapture.Sensors(), records_camera=kapture.RecordsCamera())
    for sensor_id, sensor in sensors.items():
        data.sensors[sensor_id] = sensor
    for key, name in records.items():
        data.records_camera[key] = name
        width, height = (int(v) for v in sensors[key[1]].camera_params[:2])
        path = root / "sensors" / "records_data" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.full((height, width, 3), 128, np.uint8)).save(path)
    if trajectories is not None:
        data.trajectories = kapture.Trajectories()
        for key, value in trajectories.items():
            data.trajectories[key] = value
    if rigs:
        data.rigs = kapture.Rigs()
        for key, value in rigs.items():
            data.rigs[key] = value
    if depth:
        data.records_depth = kapture.RecordsDepth()
        for key, name in depth.items():
            data.records_depth[key] = name
            path = root / "sensors" / "records_data" / name
            path.parent.mkdir(parents=True, exist_ok=True)
            np.zeros((3, 4), np.float32).tofile(path)
    kapture_csv.kapture_to_dir(str(root), data)
    return root
