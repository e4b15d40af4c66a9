"""Kapture folders -> `ImageSet` / `Scene` (LTVL submission files: `locretrieval.scene.ltvl`).

Poses are world-to-camera ``(q, t)``, ``q`` wxyz, exactly as kapture stores them in
``sensors/trajectories.txt``. A trajectory may be given per camera or per rig; for a rig it
is ``rig_from_world`` and ``sensors/rigs.txt`` holds ``cam_from_rig``, so
``cam_from_world = cam_from_rig o rig_from_world``.

Each text file is read once (`read_csv_rows`, split as ``kapture.io.csv`` splits it), its rows
validated (``_check_*``: errors name ``file:line``, which kapture's readers, which skip or crash on
bad lines, do not), then turned into kapture's poses, rigs and trajectories and our cameras.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import kapture
import kapture.io.csv as kapture_csv
import numpy as np
import quaternion

from locretrieval import geometry, limits
from locretrieval.errors import DataFileError
from locretrieval.scene.images import check_image_sizes, check_inside, check_names
from locretrieval.scene.ltvl import KaptureNames, LtvlNames
from locretrieval.scene.names import records_name_problem
from locretrieval.scene.types import CAMERA_MODELS, Camera, ImageSet, Scene

log = logging.getLogger(__name__)

SENSORS_FILE = Path(kapture_csv.CSV_FILENAMES[kapture.Sensors])
RIGS_FILE = Path(kapture_csv.CSV_FILENAMES[kapture.Rigs])
TRAJECTORIES_FILE = Path(kapture_csv.CSV_FILENAMES[kapture.Trajectories])
RECORDS_CAMERA_FILE = Path(kapture_csv.CSV_FILENAMES[kapture.RecordsCamera])
RECORDS_DEPTH_FILE = Path(kapture_csv.CSV_FILENAMES[kapture.RecordsDepth])
RECORDS_DATA_DIR = Path("sensors", "records_data")
SENSORS_DIR = Path("sensors")
#: Records files the benchmark reads; others (lidar, wifi, gnss, ...) are warned about.
READ_RECORDS = {RECORDS_CAMERA_FILE.name, RECORDS_DEPTH_FILE.name}
#: locretrieval extensions to the kapture layout (written by the synthetic renderer).
TAGS_FILE = Path("tags.txt")
#: Sensor types kapture defines (``kapture.SensorType``); others are warned about.
KNOWN_SENSOR_TYPES = {sensor_type.name for sensor_type in kapture.SensorType}
MASKS_DIR = Path("masks")
#: Suffix of the depth sensor paired with a camera: ``<camera_id>_depth``.
DEPTH_SENSOR_SUFFIX = "_depth"


class KaptureFormatError(DataFileError):
    """A line of a kapture text file that cannot be used."""

    def __init__(self, path: Path, line: int, text: str, problem: str) -> None:
        super().__init__(f"{path}:{line}", f"{problem} (line: {text.strip()[:200]!r})")


def _text_lines(path: Path) -> Iterator[tuple[int, str]]:
    """``(number, text)`` of each line of a kapture text file (UTF-8, as kapture writes it); a byte
    sequence that is not UTF-8 is a `KaptureFormatError` naming its line."""
    with path.open("rb") as stream:
        for number, raw in enumerate(stream, start=1):
            try:
                yield number, raw.decode("utf-8")
            except UnicodeDecodeError as error:
                raise KaptureFormatError(
                    path,
                    number,
                    raw.decode("utf-8", "replace"),
                    f"not UTF-8 text ({error.reason} at byte {error.start})",
                ) from None


@dataclass(frozen=True)
class CsvRow:
    path: Path
    line: int
    text: str
    fields: list[str]

    def error(self, problem: str) -> KaptureFormatError:
        return KaptureFormatError(self.path, self.line, self.text, problem)

    def timestamp(self) -> int:
        try:
            return int(self.fields[0])
        except ValueError:
            raise self.error(f"timestamp {self.fields[0]!r} is not an integer") from None

    def floats(self, start: int, stop: int, what: str) -> list[float]:
        try:
            return [float(value) for value in self.fields[start:stop]]
        except ValueError:
            raise self.error(f"non-numeric {what} {self.fields[start:stop]}") from None


def read_csv_rows(path: Path, min_fields: int, max_fields: int | None) -> list[CsvRow]:
    """Non-comment lines of a kapture CSV file, split like kapture does, field counts checked; at most
    ``limits.kapture_rows`` of them (a `KaptureFormatError` at the first line past it)."""
    rows = []
    most = limits.current().kapture_rows
    for number, text in _text_lines(path):
        if not text.strip() or text.lstrip().startswith("#"):
            continue
        if len(rows) == most:
            raise _too_many_rows(path, number, text, most)
        fields = [value.strip() for value in text.split(",")]
        if len(fields) < min_fields or (max_fields is not None and len(fields) > max_fields):
            expected = str(min_fields) if min_fields == max_fields else f"at least {min_fields}"
            raise KaptureFormatError(
                path, number, text, f"expected {expected} comma-separated fields, got {len(fields)}"
            )
        rows.append(CsvRow(path, number, text, fields))
    return rows


def _too_many_rows(path: Path, number: int, text: str, most: int) -> KaptureFormatError:
    return KaptureFormatError(
        path, number, text, f"more than {most} rows (limits.kapture_rows; raise it for a larger dataset)"
    )


def _check_unique(rows: list[CsvRow], key_fields: int, what: str) -> None:
    seen: dict[tuple[str, ...], int] = {}
    for row in rows:
        key = tuple(row.fields[:key_fields])
        if key in seen:
            raise row.error(f"duplicate {what} {key} (first on line {seen[key]})")
        seen[key] = row.line


def _check_unique_timestamps(rows: list[CsvRow], what: str) -> None:
    """Raise if two rows share ``(timestamp, id)``, timestamps compared as the integers kapture
    parses (``02`` and ``2`` are the same), naming both lines."""
    seen: dict[tuple[int, str], CsvRow] = {}
    for row in rows:
        key = (row.timestamp(), row.fields[1])
        if key in seen:
            first = seen[key]
            raise row.error(
                f"duplicate {what} {key}: also on line {first.line} "
                f"({first.text.strip()!r}); kapture would keep only one"
            )
        seen[key] = row


def _check_poses(rows: list[CsvRow], start: int) -> None:
    """Fields ``qw, qx, qy, qz, tx, ty, tz`` from ``start``: numbers and unit quaternions.

    kapture allows an empty rotation or translation (a partial pose); those stay empty.
    """
    rotations, rotation_rows, translations, translation_rows = [], [], [], []
    for row in rows:
        rotation, translation = row.fields[start : start + 4], row.fields[start + 4 : start + 7]
        for group, name in ((rotation, "rotation"), (translation, "translation")):
            if any(group) and not all(group):
                raise row.error(f"{name} is partly empty")
        if all(rotation):
            rotations.append(row.floats(start, start + 4, "quaternion"))
            rotation_rows.append(row)
        if all(translation):
            translations.append(row.floats(start + 4, start + 7, "translation"))
            translation_rows.append(row)
    bad = geometry.invalid_quaternion_rows(np.array(rotations).reshape(-1, 4))
    if bad.size:
        norm = np.linalg.norm(rotations[bad[0]])
        raise rotation_rows[bad[0]].error(
            f"quaternion (qw, qx, qy, qz) is not a finite unit quaternion "
            f"(norm {norm:.6g}, tolerance {geometry.UNIT_NORM_TOLERANCE})"
        )
    infinite = np.flatnonzero(~np.isfinite(np.array(translations).reshape(-1, 3)).all(axis=1))
    if infinite.size:
        raise translation_rows[infinite[0]].error("translation is not finite")


def _check_sensors(path: Path) -> dict[str, CsvRow]:
    """Sensor id -> its line; camera and depth sensors must have a kapture model and its parameters."""
    rows = read_csv_rows(path, 3, None)
    _check_unique(rows, 1, "sensor id")
    unknown = sorted({row.fields[2] for row in rows} - KNOWN_SENSOR_TYPES)
    if unknown:
        log.warning("%s: sensor types unknown to kapture, not used by the benchmark: %s", path, unknown)
    for row in rows:
        if row.fields[2] not in kapture.ALL_CAMERA_SENSOR_TYPES:
            continue
        if len(row.fields) < 4 or row.fields[3] not in kapture.CameraType.__members__:
            model = row.fields[3] if len(row.fields) > 3 else ""
            raise row.error(
                f"sensor {row.fields[0]!r}: unknown camera model {model!r}; kapture models: "
                f"{sorted(kapture.CameraType.__members__)}"
            )
        expected = kapture.CAMERA_TYPE_PARAMS_COUNT[kapture.CameraType[row.fields[3]]]
        if len(row.fields) - 4 != expected:
            raise row.error(
                f"sensor {row.fields[0]!r}: camera model {row.fields[3]} takes "
                f"{expected} values (width, height, parameters), got {len(row.fields) - 4}"
            )
        row.floats(4, len(row.fields), "camera parameters")
    return {row.fields[0]: row for row in rows}


def _check_rigs(path: Path, sensors: dict[str, CsvRow]) -> list[CsvRow]:
    """Rig lines must be well formed; members without a line in ``sensors.txt`` are allowed (a
    rig may describe more cameras than a recording holds, as kapture allows) and warned about."""
    rows = read_csv_rows(path, 9, 9)
    _check_unique(rows, 2, "rig/sensor pair")
    rig_ids = {row.fields[0] for row in rows}
    for row in rows:
        rig_id, sensor_id = row.fields[:2]
        if rig_id in sensors:
            raise row.error(f"rig id {rig_id!r} is also a sensor id in {sensors[rig_id].path}")
        if sensor_id in rig_ids:
            raise row.error(f"nested rig {sensor_id!r} in rig {rig_id!r} is not supported")
        if not all(row.fields[2:]):
            raise row.error(f"rig {rig_id!r}: the pose of sensor {sensor_id!r} has empty fields")
    _check_poses(rows, 2)
    absent = sorted({f"{row.fields[0]}/{row.fields[1]}" for row in rows if row.fields[1] not in sensors})
    if absent:
        log.warning(
            "%s: %d rig member(s) without a line in %s, unused: %s", path, len(absent), SENSORS_FILE, absent[:10]
        )
    return rows


def _check_trajectories(path: Path, devices: set[str]) -> list[CsvRow]:
    rows = read_csv_rows(path, 9, 9)
    _check_unique_timestamps(rows, "(timestamp, device)")
    for row in rows:
        row.timestamp()
        if row.fields[1] not in devices:
            raise row.error(
                f"trajectory for unknown sensor or rig {row.fields[1]!r} (not in {SENSORS_FILE} or {RIGS_FILE})"
            )
    _check_poses(rows, 2)
    return rows


def _check_records(path: Path, sensors: dict[str, CsvRow], sensor_types: tuple[str, ...]) -> list[CsvRow]:
    rows = read_csv_rows(path, 3, 3)
    _check_unique_timestamps(rows, "(timestamp, sensor)")
    for row in rows:
        row.timestamp()
        sensor = sensors.get(row.fields[1])
        if sensor is None:
            raise row.error(f"record of unknown sensor {row.fields[1]!r} (not in {SENSORS_FILE})")
        if sensor.fields[2] not in sensor_types:
            raise row.error(
                f"sensor {row.fields[1]!r} is of type {sensor.fields[2]!r}, expected {' or '.join(sensor_types)}"
            )
        problem = records_name_problem(row.fields[2])
        if problem:
            raise row.error(f"file name {row.fields[2][:200]!r} {problem}")
    return rows


def _check_camera_supported(sensor: CsvRow) -> None:
    model = sensor.fields[3]
    if model not in CAMERA_MODELS:
        raise sensor.error(
            f"camera {sensor.fields[0]!r} has model {model}, which locretrieval cannot use; "
            f"supported (calibrated COLMAP) models: {sorted(CAMERA_MODELS)}"
        )
    width, height = sensor.floats(4, 6, "image size")
    if not (width.is_integer() and height.is_integer() and width > 0 and height > 0):
        raise sensor.error(f"camera {sensor.fields[0]!r}: image size {width} x {height} is not a positive integer size")
    params = sensor.floats(6, len(sensor.fields), "camera parameters")
    if not all(np.isfinite(params)):
        raise sensor.error(f"camera {sensor.fields[0]!r}: parameters {params} must all be finite")
    focal = [params[i] for i in CAMERA_MODELS[model][:2]]
    if not all(f > 0 for f in focal):
        raise sensor.error(f"camera {sensor.fields[0]!r}: focal length(s) {focal} must be positive pixels")
    cx, cy = (params[i] for i in CAMERA_MODELS[model][2:])
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise sensor.error(
            f"camera {sensor.fields[0]!r}: principal point ({cx}, {cy}) lies outside the {width:g} x {height:g} "
            "image (pixels, COLMAP's convention)"
        )


def _camera(sensor: CsvRow) -> Camera:
    """The camera of a checked ``sensors.txt`` row (`_check_camera_supported`)."""
    width, height, *params = sensor.floats(4, len(sensor.fields), "camera parameters")
    return Camera(sensor.fields[3], int(width), int(height), tuple(params))


def _pose(row: CsvRow, start: int) -> kapture.PoseTransform:
    """The pose in fields ``qw, qx, qy, qz, tx, ty, tz`` from ``start`` of a checked row (`_check_poses`);
    an empty rotation or translation stays unknown (``None``), as kapture reads it."""
    rotation, translation = row.fields[start : start + 4], row.fields[start + 4 : start + 7]
    return kapture.PoseTransform(
        row.floats(start, start + 4, "quaternion") if all(rotation) else None,
        row.floats(start + 4, start + 7, "translation") if all(translation) else None,
    )


def _rigs(rows: Sequence[CsvRow]) -> kapture.Rigs:
    """``rig_id -> sensor_id -> cam_from_rig`` of the checked rows of ``rigs.txt``."""
    rigs = kapture.Rigs()
    for row in rows:
        rigs[row.fields[0], row.fields[1]] = _pose(row, 2)
    return rigs


def _trajectories(rows: Sequence[CsvRow]) -> kapture.Trajectories:
    """``timestamp -> device_id -> device_from_world`` of the checked rows of ``trajectories.txt``."""
    trajectories = kapture.Trajectories()
    for row in rows:
        trajectories.setdefault(row.timestamp(), {})[row.fields[1]] = _pose(row, 2)
    return trajectories


def _pose_arrays(poses: Sequence[kapture.PoseTransform | None]) -> tuple[np.ndarray, np.ndarray]:
    """``q [N, 4]`` (wxyz) and ``t [N, 3]``; NaN rows where the pose or a part of it is unknown."""
    q = np.full((len(poses), 4), np.nan)
    t = np.full((len(poses), 3), np.nan)
    known = [i for i, pose in enumerate(poses) if pose is not None and pose.r is not None and pose.t is not None]
    if known:
        q[known] = quaternion.as_float_array(np.array([poses[i].r for i in known]))
        t[known] = np.array([poses[i].t for i in known]).reshape(-1, 3)
    return q, t


def _inverse_poses(q: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``b_from_a`` of poses ``a_from_b`` (wxyz, t): ``(q*, -R^T t)``."""
    return geometry.quaternion_conjugate(q), geometry.camera_centers(q, t)


def _image_poses(
    keys: list[tuple[int, str]], trajectories: kapture.Trajectories, rigs: kapture.Rigs
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera poses of the images ``(timestamp, camera_id)``; NaN without a trajectory.

    A camera's own trajectory wins. Otherwise, for the first rig holding the camera that has
    a trajectory at that timestamp, ``cam_from_world = cam_from_rig o rig_from_world``; when
    only another camera of the rig has one (RobotCar Seasons v2 gives the rear camera's pose
    only), ``rig_from_world = (other_from_rig)^-1 o other_from_world``.
    """
    own = [trajectories.get(ts, {}).get(camera) for ts, camera in keys]
    partial = sum(pose is not None and (pose.r is None or pose.t is None) for pose in own)
    if partial:
        log.warning("%d images have a partial pose (empty rotation or translation); their pose is unknown", partial)
    q, t = _pose_arrays(own)
    camera_rigs: dict[str, list[str]] = {}
    for rig_id, members in rigs.items():
        for sensor_id in members:
            camera_rigs.setdefault(sensor_id, []).append(rig_id)
    identity = kapture.PoseTransform()
    rows, cam_from_rig, anchor_from_rig, anchor_from_world = [], [], [], []
    for i, (ts, camera) in enumerate(keys):
        if own[i] is not None:
            continue
        poses_at_ts = trajectories.get(ts, {})
        for rig_id in camera_rigs.get(camera, []):
            anchor = rig_id if rig_id in poses_at_ts else next((s for s in rigs[rig_id] if s in poses_at_ts), None)
            if anchor is not None:
                rows.append(i)
                cam_from_rig.append(rigs[rig_id][camera])
                anchor_from_rig.append(identity if anchor == rig_id else rigs[rig_id][anchor])
                anchor_from_world.append(poses_at_ts[anchor])
                break
    if rows:
        rig_from_world = geometry.compose_poses(
            *_inverse_poses(*_pose_arrays(anchor_from_rig)), *_pose_arrays(anchor_from_world)
        )
        q[rows], t[rows] = geometry.compose_poses(*_pose_arrays(cam_from_rig), *rig_from_world)
    return q, t


def _read_tags_file(path: Path, names: list[str]) -> list[set[str]]:
    """Per-image tags from ``tags.txt`` (``# image_name, tags`` then ``name, tag1 tag2 ...``)."""
    index = {name: i for i, name in enumerate(names)}
    tags: list[set[str]] = [set() for _ in names]
    rows, most = 0, limits.current().kapture_rows
    for number, text in _text_lines(path):
        if not text.strip() or text.lstrip().startswith("#"):
            continue
        rows += 1
        if rows > most:
            raise _too_many_rows(path, number, text, most)
        name, separator, values = text.partition(",")
        if not separator:
            raise KaptureFormatError(path, number, text, "expected 'image_name, tag1 tag2 ...'")
        if name.strip() not in index:
            raise KaptureFormatError(path, number, text, f"image {name.strip()!r} is not in {RECORDS_CAMERA_FILE}")
        tags[index[name.strip()]].update(values.split())
    return tags


def _check_files_exist(folder: Path, names: Sequence[str], what: str) -> None:
    missing = [name for name in names if not os.path.isfile(os.path.join(folder, name))]
    if missing:
        raise FileNotFoundError(
            f"{len(missing)} {what} file(s) listed in the kapture folder are missing from {folder}, e.g. {missing[:3]}"
        )


def _depth_paths(root: Path, keys: Sequence[tuple[int, str]], sensors: dict[str, CsvRow]) -> list[Path | None] | None:
    """Depth map of each image (``records_depth.txt``, sensor ``<camera>_depth`` at its
    timestamp), or ``None`` without any. Depth is side data the benchmark does not use: entries
    of unknown sensors or with missing files are warned about and left out (malformed lines are
    still errors)."""
    path = root / RECORDS_DEPTH_FILE
    if not path.is_file():
        return None
    usable, skipped = {}, []
    for row in read_csv_rows(path, 3, 3):
        sensor = sensors.get(row.fields[1])
        if (
            sensor is None
            or sensor.fields[2] not in kapture.ALL_CAMERA_SENSOR_TYPES
            or not (root / RECORDS_DATA_DIR / row.fields[2]).is_file()
        ):
            skipped.append(row)
            continue
        usable[(row.timestamp(), row.fields[1])] = root / RECORDS_DATA_DIR / row.fields[2]
    if skipped:
        log.warning(
            "%s: %d depth record(s) left out (unknown sensor or missing file), e.g. line %d: %r",
            path,
            len(skipped),
            skipped[0].line,
            skipped[0].text,
        )
    paths = [usable.get((ts, camera + DEPTH_SENSOR_SUFFIX)) for ts, camera in keys]
    return paths if any(paths) else None


def load_image_set(kapture_root: str | Path, tag: str | None = None) -> ImageSet:
    """The images of one kapture folder, in (timestamp, sensor id) order.

    Names are as ``records_camera.txt`` lists them, relative to ``image_root =
    <kapture_root>/sensors/records_data``. Poses are world-to-camera (wxyz, t), NaN for images
    without a trajectory (or without ``trajectories.txt``). ``tag`` is added to every image,
    plus the per-image tags of ``<kapture_root>/tags.txt``. Depth maps come from
    ``records_depth.txt`` entries of sensor ``<camera_id>_depth`` at the image's timestamp,
    masks from ``<kapture_root>/masks/<image name>``. Principal points are kept as stated.
    """
    root = Path(kapture_root)
    for required in (SENSORS_FILE, RECORDS_CAMERA_FILE):
        if not (root / required).is_file():
            raise FileNotFoundError(f"not a kapture folder: {root / required} is missing")
    sensors = _check_sensors(root / SENSORS_FILE)
    rigs = _rigs(_check_rigs(root / RIGS_FILE, sensors)) if (root / RIGS_FILE).is_file() else kapture.Rigs()
    records = _check_records(root / RECORDS_CAMERA_FILE, sensors, ("camera",))
    if not records:
        raise DataFileError(root / RECORDS_CAMERA_FILE, "lists no image")
    for camera_id in {row.fields[1] for row in records}:
        _check_camera_supported(sensors[camera_id])
    trajectories = kapture.Trajectories()
    if (root / TRAJECTORIES_FILE).is_file():
        trajectories = _trajectories(_check_trajectories(root / TRAJECTORIES_FILE, set(sensors) | set(rigs)))
    unused = sorted(path.name for path in (root / SENSORS_DIR).glob("records_*.txt") if path.name not in READ_RECORDS)
    if unused:
        log.warning("%s: records not used by the benchmark: %s", root / SENSORS_DIR, unused)

    entries = sorted((row.timestamp(), row.fields[1], row.fields[2]) for row in records)  # kapture's order
    keys = [(ts, camera) for ts, camera, _ in entries]
    names = [name for _, _, name in entries]
    duplicates = sorted(name for name, count in Counter(names).items() if count > 1)
    if duplicates:
        raise DataFileError(root / RECORDS_CAMERA_FILE, f"image file(s) listed more than once: {duplicates[:3]}")
    check_names(root / RECORDS_CAMERA_FILE, names)
    image_root = root / RECORDS_DATA_DIR
    _check_files_exist(image_root, names, "image")
    check_inside(root, image_root, names, "kapture folder")
    cameras = {camera: _camera(sensors[camera]) for camera in {c for _, c in keys}}
    check_image_sizes(image_root, names, [cameras[c] for _, c in keys], [f"{c!r} in {SENSORS_FILE}" for _, c in keys])
    qvec, tvec = _image_poses(keys, trajectories, rigs)

    depth_paths = _depth_paths(root, keys, sensors)
    mask_paths = None
    if (root / MASKS_DIR).is_dir():
        masks = root / MASKS_DIR
        mask_paths = [masks / name if os.path.isfile(os.path.join(masks, name)) else None for name in names]

    tags = _read_tags_file(root / TAGS_FILE, names) if (root / TAGS_FILE).is_file() else [set() for _ in names]
    if tag:
        for image_tags in tags:
            image_tags.add(tag)
    return ImageSet(
        names=names,
        image_root=image_root,
        cameras=[cameras[camera] for _, camera in keys],
        qvec=qvec,
        tvec=tvec,
        tags=[frozenset(t) for t in tags],
        depth_paths=depth_paths,
        mask_paths=mask_paths,
    )


def concatenate_image_sets(image_sets: Sequence[ImageSet]) -> ImageSet:
    """One set holding several (e.g. Aachen's query_day and query_night), in order.

    Every image keeps its own root (``ImageSet.image_roots``); ``image_root`` becomes the
    folders' common parent. Image names must be unique across the sets.
    """
    if len(image_sets) == 1:
        return image_sets[0]
    if not image_sets:
        raise ValueError("no image set to concatenate")
    folder_of: dict[str, Path] = {}
    for image_set in image_sets:
        for name in image_set.names:
            if name in folder_of:
                raise ValueError(f"image name {name!r} is in both {folder_of[name]} and {image_set.image_root}")
            folder_of[name] = image_set.image_root

    def joined(attribute: str) -> list | None:
        values = [getattr(image_set, attribute) for image_set in image_sets]
        if all(value is None for value in values):
            return None
        return [x for image_set, value in zip(image_sets, values) for x in (value or [None] * len(image_set))]

    return ImageSet(
        names=[name for image_set in image_sets for name in image_set.names],
        image_root=Path(os.path.commonpath([image_set.image_root for image_set in image_sets])),
        cameras=[camera for image_set in image_sets for camera in image_set.cameras],
        qvec=np.concatenate([image_set.qvec for image_set in image_sets]),
        tvec=np.concatenate([image_set.tvec for image_set in image_sets]),
        tags=[tags for image_set in image_sets for tags in image_set.tags],
        depth_paths=joined("depth_paths"),
        mask_paths=joined("mask_paths"),
        image_roots=[
            root
            for image_set in image_sets
            for root in (image_set.image_roots or [image_set.image_root] * len(image_set))
        ],
    )


def add_name_tags(image_set: ImageSet, patterns: Mapping[str, str]) -> ImageSet:
    """The set with ``tag`` added to every image whose name matches its regular expression
    (``re.search``), e.g. RobotCar's ``{"night": "^night(-rain)?/"}``."""
    compiled = {}
    for tag, pattern in patterns.items():
        try:
            compiled[tag] = re.compile(pattern)
        except re.error as error:
            raise ValueError(f"name tag {tag!r}: invalid regular expression {pattern!r}: {error}") from error
    tags = [
        tags | {tag for tag, regex in compiled.items() if regex.search(name)}
        for name, tags in zip(image_set.names, image_set.tags)
    ]
    return dataclasses.replace(image_set, tags=tags)


def _posed_database(image_set: ImageSet, folders: Sequence[Path]) -> ImageSet:
    """Mapping images that can serve as database images: those with a pose (others logged)."""
    posed = image_set.has_pose
    if not posed.all():
        unposed = [name for name, ok in zip(image_set.names, posed) if not ok]
        log.warning(
            "%d of %d mapping images in %s have no pose and are left out of the database, e.g. %s",
            len(unposed),
            len(image_set),
            ", ".join(map(str, folders)),
            unposed[:3],
        )
    return image_set.subset(posed)


def _check_disjoint(database: ImageSet, queries: ImageSet) -> None:
    """Raise when a query image is a database image (the same file, through any path or link): a
    query folder that is (or shares images with) the mapping folder would be found by every ranking."""
    files = {}
    for path in database.paths:
        status = os.stat(path)
        files[(status.st_dev, status.st_ino)] = path
    for path in queries.paths:
        status = os.stat(path)
        same = files.get((status.st_dev, status.st_ino))
        if same is not None:
            raise ValueError(
                f"query image {path} is the database image {same}: the query folders must hold other images than "
                "the mapping folders (data.queries and data.mapping)"
            )


def load_kapture_scene(
    name: str,
    mapping: str | Path | Sequence[str | Path],
    queries: Sequence[str | Path],
    *,
    query_tags: Sequence[str] | None = None,
    name_tags: Mapping[str, str] | None = None,
    ltvl_names: LtvlNames | None = None,
    frustum_far: float | None = None,
) -> Scene:
    """A scene from kapture folders: database from the mapping folder(s), queries from the
    query folders (concatenated, names unique).

    Each query folder's images are tagged with ``query_tags`` (default: the folder name, e.g.
    ``query_day``); ``name_tags`` ``{tag: regex}`` tag database and query images by name.
    Mapping images without a pose are left out of the database (logged).
    ``Scene.sources`` lists all folders; ``ltvl_names`` (None: kapture's names) and
    ``frustum_far`` are kept on the `Scene`.
    """
    mapping_folders = [Path(mapping)] if isinstance(mapping, (str, Path)) else [Path(folder) for folder in mapping]
    query_folders = [Path(folder) for folder in queries]
    if not mapping_folders or not query_folders:
        raise ValueError(
            f"scene {name!r} needs at least one mapping and one query folder, got {mapping_folders} and {query_folders}"
        )
    tags = [folder.name for folder in query_folders] if query_tags is None else list(query_tags)
    if len(tags) != len(query_folders):
        raise ValueError(f"scene {name!r}: {len(tags)} query tags {tags} for {len(query_folders)} query folders")
    database = _posed_database(
        concatenate_image_sets([load_image_set(folder) for folder in mapping_folders]), mapping_folders
    )
    query_set = concatenate_image_sets([load_image_set(folder, tag) for folder, tag in zip(query_folders, tags)])
    _check_disjoint(database, query_set)
    if name_tags:
        database, query_set = add_name_tags(database, name_tags), add_name_tags(query_set, name_tags)
    sources = mapping_folders + query_folders
    return Scene(name, database, query_set, sources, ltvl_names or KaptureNames(), frustum_far)
