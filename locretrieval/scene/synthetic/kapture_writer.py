"""Writing one rendered image set as a kapture folder (with the ``kapture`` library).

Layout of ``<root>`` (kapture 1.1):

- ``sensors/sensors.txt``: one camera per :class:`PinholeCamera` and a depth sensor
  ``<camera_id>_depth`` with the same intrinsics;
- ``sensors/trajectories.txt``: world-to-camera poses (qw, qx, qy, qz, tx, ty, tz) of every
  image, repeated for its depth map (same timestamp, depth sensor id);
- ``sensors/records_camera.txt`` / ``records_depth.txt`` and the files under
  ``sensors/records_data/``: ``<set>/<index>.png`` images and ``<set>/<index>.depth`` float32
  z-depth maps in metres (0 = no depth, e.g. sky);
- ``masks/<image name>``: uint8 PNG, 255 on dynamic objects, 0 elsewhere;
- ``tags.txt``: ``# image_name, tags`` then ``<image name>, <space-separated tags>``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import kapture
import kapture.io.csv as kapture_csv
import kapture.io.records as kapture_records
import numpy as np
from PIL import Image

from locretrieval import geometry
from locretrieval.scene.kapture_io import DEPTH_SENSOR_SUFFIX, MASKS_DIR, TAGS_FILE
from locretrieval.scene.synthetic.camera import PinholeCamera

TAGS_HEADER = "# image_name, tags"


def depth_sensor_id(camera_id: str) -> str:
    return f"{camera_id}{DEPTH_SENSOR_SUFFIX}"


def depth_name(image_name: str) -> str:
    """Depth map file name (relative to records_data) of an image."""
    return str(Path(image_name).with_suffix(".depth"))


@dataclass(frozen=True)
class WrittenImage:
    """What the kapture files list about one image already written to disk."""

    name: str
    timestamp: int
    camera_id: str
    rotation: np.ndarray  # world-to-camera
    center: np.ndarray
    tags: tuple[str, ...]


def write_image_files(root: Path, name: str, rgb: np.ndarray, depth: np.ndarray, mask: np.ndarray) -> None:
    """The image (uint8 RGB PNG), its depth map (kapture binary float32) and its dynamic mask."""
    image_path = Path(kapture_records.get_image_fullpath(str(root), name))
    image_path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb).save(image_path, compress_level=1)
    kapture_records.depth_map_to_file(
        kapture_records.get_depth_map_fullpath(str(root), depth_name(name)), depth.astype(kapture.RecordsDepth.dtype)
    )
    mask_path = root / MASKS_DIR / name
    mask_path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.where(mask, 255, 0).astype(np.uint8)).save(mask_path, compress_level=1)


def write_kapture_lists(root: Path, cameras: list[PinholeCamera], images: list[WrittenImage]) -> None:
    """Sensors, trajectories, camera and depth records, and ``tags.txt``."""
    sensors = kapture.Sensors()
    for camera in cameras:
        params = [camera.width, camera.height, *camera.params]
        sensors[camera.sensor_id] = kapture.Camera(camera.model, params, name=camera.sensor_id)
        depth_id = depth_sensor_id(camera.sensor_id)
        sensors[depth_id] = kapture.Camera(camera.model, params, name=depth_id, sensor_type="depth")
    trajectories = kapture.Trajectories()
    records_camera = kapture.RecordsCamera()
    records_depth = kapture.RecordsDepth()
    for image in images:
        q = geometry.matrix_to_quaternion(image.rotation)
        t = -image.rotation @ image.center
        pose = kapture.PoseTransform(r=list(q), t=list(t))
        depth_id = depth_sensor_id(image.camera_id)
        trajectories[image.timestamp, image.camera_id] = pose
        trajectories[image.timestamp, depth_id] = pose
        records_camera[image.timestamp, image.camera_id] = image.name
        records_depth[image.timestamp, depth_id] = depth_name(image.name)
    root.mkdir(parents=True, exist_ok=True)
    data = kapture.Kapture(
        sensors=sensors, trajectories=trajectories, records_camera=records_camera, records_depth=records_depth
    )
    kapture_csv.kapture_to_dir(str(root), data)
    lines = [TAGS_HEADER] + [f"{image.name}, {' '.join(image.tags)}" for image in images]
    (root / TAGS_FILE).write_text("\n".join(lines) + "\n")
