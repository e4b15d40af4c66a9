"""A COLMAP model's files checked before pycolmap reads them, and the model it read checked like a
kapture folder.

pycolmap trusts a model's counts: it reserves what a record declares before reading it and reads
past the end of a file without noticing (a 0-byte ``points3D.bin`` reached 2.27 GB before a
``bad_alloc``; a name without its terminating zero byte is read forever). So before it reads a
binary model (`check_model_files`), every record of its files (``rigs``, ``cameras``, ``frames``,
``images``, ``points3D``, ``.bin``: COLMAP's little-endian layout, the reader's) is walked: each
count must fit in the bytes left, each camera model be one pycolmap knows, each name end within
the file, and the file end with its last record; what pycolmap then allocates is bounded by the
file's bytes. A text model needs no such walk: pycolmap's text reader checks each line's fields as
it parses them, and what it builds is bounded by its lines.

The model read is then checked (`check_reconstruction`), as kapture's ``sensors.txt`` and
trajectories are: each camera a model locretrieval reads with finite parameters, positive focal
lengths and its principal point within the image; each image's name UTF-8 text; each registered
image's pose a finite unit quaternion (within `geometry.UNIT_NORM_TOLERANCE`; normalised where it
is read) and a finite translation. Every refusal is a `DataFileError` naming the file, and the
camera, image or record.
"""

from __future__ import annotations

import functools
import mmap
import os
import struct
from pathlib import Path
from typing import Any

import numpy as np

from locretrieval import geometry
from locretrieval.errors import FIX_DATA_FILE, DataFileError
from locretrieval.scene.types import CAMERA_MODELS

#: The files pycolmap reads, in its order; ``rigs`` and ``frames`` are optional (models before COLMAP 3.12).
READ_ORDER = ("rigs", "cameras", "frames", "images", "points3D")
REQUIRED = ("cameras", "images", "points3D")


def model_files(folder: Path) -> dict[str, Path]:
    """The files of the model ``folder`` pycolmap reads, by name: the binary ones when the three
    `REQUIRED` ``.bin`` files are there, else the text ones (as ``Reconstruction.Read`` chooses)."""
    binary = all((folder / f"{name}.bin").is_file() for name in REQUIRED)
    suffix = ".bin" if binary else ".txt"
    return {name: folder / f"{name}{suffix}" for name in READ_ORDER if (folder / f"{name}{suffix}").is_file()}


def check_model_files(folder: Path) -> None:
    """Walk the records of the model ``folder``'s binary files before pycolmap reads them (module docstring)."""
    for name, path in model_files(folder).items():
        if path.suffix == ".bin":
            with _Records(path) as records:
                BINARY_CHECKS[name](records)


class _Records:
    """A binary file read as little-endian records, each read within its bytes (mapped, not loaded)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.position = 0
        self.stream = open(path, "rb")  # closed by __exit__
        self.size = os.fstat(self.stream.fileno()).st_size
        self.data: Any = mmap.mmap(self.stream.fileno(), 0, access=mmap.ACCESS_READ) if self.size else b""

    def __enter__(self) -> _Records:
        return self

    def __exit__(self, *exception: Any) -> None:
        if isinstance(self.data, mmap.mmap):
            self.data.close()
        self.stream.close()

    def error(self, problem: str) -> DataFileError:
        return DataFileError(self.path, f"{problem}; pycolmap would read past what the file holds", FIX_DATA_FILE)

    def read(self, layout: str, what: str) -> tuple:
        """The values of ``layout`` (a `struct` format, little-endian) at the current position."""
        size = struct.calcsize(layout)
        if self.position + size > self.size:
            raise self.error(f"cut short in {what} (byte {self.position} of {self.size})")
        values = struct.unpack_from(layout, self.data, self.position)
        self.position += size
        return values

    def fits(self, count: int, record_bytes: int, what: str) -> None:
        """Raise unless the bytes left hold ``count`` records of ``record_bytes`` (at least) each."""
        left = self.size - self.position
        if count * record_bytes > left:
            raise self.error(f"{what} declares {count} entries of {record_bytes} bytes, but {left} bytes are left")

    def skip(self, count: int, record_bytes: int, what: str) -> None:
        """Pass ``count`` records of ``record_bytes`` each (`fits`)."""
        self.fits(count, record_bytes, what)
        self.position += count * record_bytes

    def count(self, least_bytes: int, what: str) -> int:
        """The record count at the start of the file, refused when the bytes left cannot hold that
        many records of at least ``least_bytes``."""
        (count,) = self.read("<Q", f"the number of {what}")
        self.fits(count, least_bytes, f"its header ({what})")
        return count

    def counted(self, count: int, header: struct.Struct, entry_bytes: int, what: str) -> None:
        """Pass ``count`` records of a fixed ``header`` whose last field counts the entries of
        ``entry_bytes`` each that follow it (a 3D point's track, a frame's data ids): the loop of
        the largest files, kept lean."""
        unpack, header_bytes, position, size = header.unpack_from, header.size, self.position, self.size
        for index in range(count):
            if position + header_bytes > size:
                raise self.error(f"cut short in {what} {index} (byte {position} of {size})")
            entries = unpack(self.data, position)[-1]
            position += header_bytes + entries * entry_bytes
            if position > size:
                raise self.error(
                    f"{what} {index} declares {entries} entries of {entry_bytes} bytes past the file's end"
                )
        self.position = position

    def name(self, what: str) -> None:
        """Pass a zero-terminated name."""
        end = self.data.find(b"\0", self.position)
        if end < 0:
            raise self.error(f"the name of {what} has no terminating zero byte before the end of the file")
        self.position = end + 1

    def finished(self) -> None:
        if self.position != self.size:
            raise DataFileError(
                self.path, f"{self.size - self.position} bytes follow its last record (a damaged file)", FIX_DATA_FILE
            )


#: Bytes of a rig sensor without its pose (type, id, has_pose), of a pose (quaternion wxyz, translation).
SENSOR_BYTES, POSE_BYTES = 9, 56


def _check_rigs(records: _Records) -> None:
    for index in range(records.count(8, "rigs")):
        rig_id, sensors = records.read("<II", f"rig {index}")
        if sensors == 0:
            continue
        records.read("<iI", f"rig {rig_id}'s reference sensor")
        records.fits(sensors - 1, SENSOR_BYTES, f"rig {rig_id}")
        for _ in range(sensors - 1):
            *_, has_pose = records.read("<iIB", f"a sensor of rig {rig_id}")
            if has_pose:
                records.skip(1, POSE_BYTES, f"a sensor pose of rig {rig_id}")
    records.finished()


def _check_cameras(records: _Records) -> None:
    for index in range(records.count(24, "cameras")):
        camera_id, model_id, _, _ = records.read("<IiQQ", f"camera {index}")
        parameters = camera_parameters().get(model_id)
        if parameters is None:
            raise DataFileError(
                records.path, f"camera {camera_id} has a camera model id {model_id} that pycolmap does not know"
            )
        records.skip(parameters, 8, f"camera {camera_id}'s parameters")
    records.finished()


#: A frame before its data ids (id, rig id, pose, their number), a 3D point before its track (id, xyz,
#: colour, error, its length).
FRAME, POINT = struct.Struct("<II7dI"), struct.Struct("<Q3d3BdQ")


def _check_frames(records: _Records) -> None:
    records.counted(records.count(FRAME.size, "frames"), FRAME, 16, "frame")
    records.finished()


def _check_images(records: _Records) -> None:
    for index in range(records.count(73, "images")):
        image_id, *_ = records.read("<I7dI", f"image {index}")
        records.name(f"image {image_id}")
        (points,) = records.read("<Q", f"image {image_id}'s number of 2D points")
        records.skip(points, 24, f"image {image_id}'s 2D points")
    records.finished()


def _check_points(records: _Records) -> None:
    records.counted(records.count(POINT.size, "3D points"), POINT, 8, "3D point")
    records.finished()


BINARY_CHECKS = {
    "rigs": _check_rigs,
    "cameras": _check_cameras,
    "frames": _check_frames,
    "images": _check_images,
    "points3D": _check_points,
}


@functools.cache
def camera_parameters() -> dict[int, int]:
    """The number of parameters of each camera model id pycolmap knows."""
    import pycolmap

    return {
        int(model): pycolmap.Camera.create_from_model_name(1, name, 1.0, 1, 1).params.size
        for name, model in pycolmap.CameraModelId.__members__.items()
        if int(model) >= 0
    }


def check_reconstruction(reconstruction: Any, folder: Path) -> None:
    """Check the cameras, image names and registered poses of the model pycolmap read from
    ``folder`` (module docstring)."""
    files = model_files(folder)
    for camera_id, camera in sorted(reconstruction.cameras.items()):
        _check_camera(camera_id, camera, files["cameras"])
    poses = files.get("frames", files["images"])  # where the poses are: a frame's, or (before rigs) the image's
    for image_id, image in sorted(reconstruction.images.items()):
        try:
            image.name  # pycolmap decodes it here
        except UnicodeDecodeError as error:
            raise DataFileError(
                files["images"], f"image {image_id}: its name is not UTF-8 text ({error.reason})", FIX_DATA_FILE
            ) from None
        if image.has_pose:
            _check_pose(image_id, image.name, image.cam_from_world(), poses)


def _check_camera(camera_id: int, camera: Any, path: Path) -> None:
    model = camera.model.name
    if model not in CAMERA_MODELS:
        raise DataFileError(
            path,
            f"camera {camera_id} has model {model}, which locretrieval cannot use; supported (calibrated COLMAP) "
            f"models: {sorted(CAMERA_MODELS)}",
        )
    width, height, params = int(camera.width), int(camera.height), np.asarray(camera.params, dtype=np.float64)
    problem = None
    if width <= 0 or height <= 0:
        problem = f"image size {width} x {height} is not positive"
    elif not np.isfinite(params).all():
        problem = f"parameters {params.tolist()} must all be finite"
    elif not (params[list(CAMERA_MODELS[model][:2])] > 0).all():
        problem = f"focal length(s) {params[list(CAMERA_MODELS[model][:2])].tolist()} must be positive pixels"
    else:
        cx, cy = params[list(CAMERA_MODELS[model][2:])]
        if not (0 <= cx <= width and 0 <= cy <= height):
            problem = (
                f"principal point ({cx}, {cy}) lies outside the {width} x {height} image (pixels, COLMAP's convention)"
            )
    if problem:
        raise DataFileError(path, f"camera {camera_id}: {problem}", FIX_DATA_FILE)


def _check_pose(image_id: int, name: str, cam_from_world: Any, path: Path) -> None:
    x, y, z, w = np.asarray(cam_from_world.rotation.quat, dtype=np.float64)
    quaternion, translation = np.array([w, x, y, z]), np.asarray(cam_from_world.translation, dtype=np.float64)
    problem = None
    with np.errstate(over="ignore"):  # 1e300 squared: its norm is inf, refused
        norm = float(np.linalg.norm(quaternion))
        invalid = geometry.invalid_quaternion_rows(quaternion[None]).size
    if invalid:
        problem = (
            f"pose quaternion (wxyz) {quaternion.tolist()} is not a finite unit quaternion (norm {norm:.6g}, "
            f"tolerance {geometry.UNIT_NORM_TOLERANCE})"
        )
    elif not np.isfinite(translation).all():
        problem = f"pose translation {translation.tolist()} is not finite"
    if problem:
        raise DataFileError(path, f"image {image_id} ({name!r}): {problem}", FIX_DATA_FILE)
