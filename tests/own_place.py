"""A user's own place, made for the tests: photos of a walk through the built-in synthetic mall
(rendered by the project's renderer, written as JPEG files, with GPS positions in their EXIF when
asked) and COLMAP models of known scenes written by pycolmap."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import helpers
import numpy as np
from PIL import ExifTags, Image

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.scene import Camera

#: Where the walk's east-north-up frame sits on the earth (degrees, degrees, metres).
GPS_ORIGIN = (48.85, 2.35, 40.0)


@dataclass(frozen=True)
class Walk:
    """The photos of a walk: their ``names`` in ``folder``, the one ``camera`` and the true
    world-to-camera poses (``qvec`` wxyz, ``tvec``) and camera ``centres`` (metres)."""

    folder: Path
    names: list[str]
    camera: Camera
    qvec: np.ndarray
    tvec: np.ndarray

    @property
    def centres(self) -> np.ndarray:
        return geometry.camera_centers(self.qvec, self.tvec)


def render_walk(
    folder: Path, count: int, width: int, height: int, gps: bool, length: float = 15.0, seed: int = 0
) -> Walk:
    """``count`` photos of a walk along the mall's corridor (2 m from its middle, 1.6 m high, ``length``
    metres from x = 2 m), turned 25 degrees either side of the shops across it: a phone's capture of one
    side. JPEG files ``walk/NNN.jpg`` of ``folder``; with ``gps``, each with its camera centre as
    a GPS position (the world's x, y, z as east, north, up about `GPS_ORIGIN`)."""
    import pycolmap
    import torch

    from locretrieval.scene.synthetic.camera import PinholeCamera
    from locretrieval.scene.synthetic.dataset import build_environment, single_torch_thread
    from locretrieval.scene.synthetic.render import Renderer
    from locretrieval.scene.synthetic.trajectories import Viewpoint

    environment = build_environment(helpers.render_settings({"length": 20.0, "texture_size": 128, "seed": seed}))
    renderer = Renderer(environment, torch.device("cpu"))
    camera = PinholeCamera.centred("phone", "PINHOLE", width, height, 70.0)
    rng = np.random.default_rng(seed)
    names, rotations, centres = [], [], []
    (folder / "walk").mkdir(parents=True, exist_ok=True)
    with single_torch_thread():
        for index, x in enumerate(np.linspace(2.0, 2.0 + length, count)):
            centre = np.array([x, -2.0 + rng.normal(0.0, 0.2), 1.6 + rng.normal(0.0, 0.05)])
            view = Viewpoint(centre, 90.0 + 25.0 * np.sin(1.3 * index), rng.normal(0.0, 3.0), rng.normal(0.0, 2.0))
            rgb = renderer.render(camera, view.rotation, view.center, environment.day).rgb
            name = f"walk/{index:03d}.jpg"
            exif = Image.Exif()
            if gps:
                latitude, longitude, altitude = pycolmap.GPSTransform().enu_to_ellipsoid(centre[None], *GPS_ORIGIN)[0]
                exif[ExifTags.IFD.GPSInfo] = gps_exif(latitude, longitude, altitude)
            image = Image.fromarray((np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))
            image.save(folder / name, quality=92, exif=exif)
            names.append(name)
            rotations.append(view.rotation)
            centres.append(centre)
    qvec = geometry.matrix_to_quaternion(np.array(rotations))
    tvec = geometry.translations_from_centers(qvec, np.array(centres))
    return Walk(folder, names, Camera("PINHOLE", width, height, tuple(camera.params)), qvec, tvec)


def gps_exif(latitude: float, longitude: float, altitude: float) -> dict:
    """An EXIF GPS directory (tags 1-6) of a position, seconds to 1e-6 (3 cm / 1000)."""

    def dms(angle: float) -> tuple[float, float, float]:
        angle = abs(angle)
        degrees, minutes = int(angle), int(abs(angle) * 60) % 60
        return float(degrees), float(minutes), round((angle - degrees - minutes / 60.0) * 3600.0, 6)

    return {
        1: "N" if latitude >= 0 else "S",
        2: dms(latitude),
        3: "E" if longitude >= 0 else "W",
        4: dms(longitude),
        5: b"\x00" if altitude >= 0 else b"\x01",
        6: round(abs(float(altitude)), 4),
    }


def write_model(
    folder: Path, names: list[str], camera: Camera, qvec: np.ndarray, tvec: np.ndarray, tracks: list[list[int]],
    points: np.ndarray, text: bool = False, unregistered: tuple[str, ...] = (),
) -> None:  # fmt: skip
    """A COLMAP model of a known scene written by pycolmap: one camera, the images ``names`` at their
    poses, and 3D ``points`` each observed by the images of its track (indices into ``names``) at its
    projection; ``unregistered`` images are in the model without a pose."""
    import pycolmap

    from locretrieval.scene.colmap import to_pycolmap_camera, to_rigid3d

    model = pycolmap.Reconstruction()
    model.add_camera_with_trivial_rig(to_pycolmap_camera(camera, 1))
    observed: list[list[tuple[int, np.ndarray]]] = [[] for _ in names]  # (point, pixel) of each image
    for point, track in enumerate(tracks):
        for image in track:
            observed[image].append((point, project(camera, qvec[image], tvec[image], points[point])))
    for index, name in enumerate(names):
        keypoints = np.array([pixel for _, pixel in observed[index]], dtype=np.float64).reshape(-1, 2)
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=1, image_id=index + 1)
        model.add_image_with_trivial_frame(image, to_rigid3d(qvec[index], tvec[index]))
    for offset, name in enumerate(unregistered):
        image = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=1, image_id=len(names) + offset + 1)
        model.add_image_with_trivial_frame(image, to_rigid3d(qvec[0], tvec[0]))
        model.deregister_frame(model.image(image.image_id).frame_id)
    slot = [0] * len(names)
    for point, track in enumerate(tracks):
        elements = pycolmap.Track()
        for image in track:
            elements.add_element(image + 1, slot[image])
            slot[image] += 1
        model.add_point3D(points[point], elements)
    folder.mkdir(parents=True, exist_ok=True)
    model.write_text(folder) if text else model.write(folder)


def project(camera: Camera, qvec: np.ndarray, tvec: np.ndarray, point: np.ndarray) -> np.ndarray:
    """The pixel (COLMAP's convention) where a pinhole ``camera`` at the world-to-camera pose sees ``point``."""
    fx, fy, cx, cy = camera.pinhole
    x, y, z = geometry.quaternion_to_matrix(qvec) @ point + tvec
    return np.array([fx * x / z + cx, fy * y / z + cy])


def write_truth_kapture(walk: Walk, root: Path, rows: dict[str, list[int]]) -> dict[str, Path]:
    """Kapture folders of the walk's photos at their true poses: ``rows`` maps a folder name
    (``mapping``, ``query``) to the indices of its photos; returns the folders."""
    import shutil

    import kapture
    from kapture_folders import write_kapture

    camera = kapture.Camera(kapture.CameraType.PINHOLE, [walk.camera.width, walk.camera.height, *walk.camera.params])
    folders = {}
    for folder, indices in rows.items():
        records = {(i, "phone"): walk.names[i] for i in indices}
        poses = {(i, "phone"): kapture.PoseTransform(walk.qvec[i], walk.tvec[i]) for i in indices}
        folders[folder] = write_kapture(root / folder, {"phone": camera}, records, poses)
        for i in indices:  # the photos themselves, where write_kapture put grey images
            shutil.copy(walk.folder / walk.names[i], root / folder / "sensors" / "records_data" / walk.names[i])
    return folders


def rig_model(folder: Path, text: bool = False, keypoints: int = 500) -> Path:
    """A COLMAP model as published ones are (COLMAP 3.12 and later): a rig of two cameras (OPENCV
    with its distortion, SIMPLE_RADIAL 0.1 m to its right) 64 x 48 pixels, three frames 1 m apart
    along x (identity rotations), six registered images ``cam<1|2>/<frame>.jpg`` of ``keypoints``
    2D points each, and 20 3D points each observed by the six images; written by pycolmap."""
    import pycolmap

    model = pycolmap.Reconstruction()
    for camera_id, name, params in (
        (1, "OPENCV", [50, 51, 32, 24, 0.01, -0.002, 1e-4, 2e-4]),
        (2, "SIMPLE_RADIAL", [50, 32, 24, 0.01]),
    ):
        camera = pycolmap.Camera(model=name, width=64, height=48, params=params)
        camera.camera_id = camera_id
        model.add_camera(camera)
    rig = pycolmap.Rig(rig_id=1)
    rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, 1))
    rig.add_sensor(
        pycolmap.sensor_t(pycolmap.SensorType.CAMERA, 2), pycolmap.Rigid3d(pycolmap.Rotation3d(), [0.1, 0.0, 0.0])
    )
    model.add_rig(rig)
    rng = np.random.default_rng(0)
    for frame_id in (1, 2, 3):
        frame = pycolmap.Frame()
        frame.frame_id, frame.rig_id = frame_id, 1
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(), [float(frame_id - 1), 0.0, 0.0])
        for camera_id in (1, 2):
            image_id = 2 * (frame_id - 1) + camera_id
            frame.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera_id), image_id))
        model.add_frame(frame)
        for camera_id in (1, 2):
            image_id = 2 * (frame_id - 1) + camera_id
            image = pycolmap.Image(
                name=f"cam{camera_id}/{frame_id - 1:03d}.jpg",
                keypoints=rng.uniform(0.0, 48.0, (keypoints, 2)),
                camera_id=camera_id,
                image_id=image_id,
            )
            image.frame_id = frame_id
            model.add_image(image)
        model.register_frame(frame_id)
    for point in range(20):
        track = pycolmap.Track()
        for image_id in range(1, 7):
            track.add_element(image_id, point)
        model.add_point3D(rng.uniform(-1.0, 1.0, 3) + [0.0, 0.0, 5.0], track)
    folder.mkdir(parents=True, exist_ok=True)
    model.write_text(folder) if text else model.write(folder)
    return folder


def plain_photos(
    folder: Path, centres: np.ndarray, width: int, height: int, altitudes: Sequence[float | None] | None = None
) -> list[str]:
    """One JPEG file ``walk/NNN.jpg`` of ``folder`` per camera centre (metres, east-north-up about
    `GPS_ORIGIN`), each of another flat colour (no two alike), its centre in its EXIF as a GPS
    position whose altitude is its value of ``altitudes`` where that is given; returns their names."""
    import pycolmap

    names = []
    for index, centre in enumerate(np.asarray(centres, dtype=np.float64)):
        latitude, longitude, altitude = pycolmap.GPSTransform().enu_to_ellipsoid(centre[None], *GPS_ORIGIN)[0]
        if altitudes is not None and altitudes[index] is not None:
            altitude = altitudes[index]
        exif = Image.Exif()
        exif[ExifTags.IFD.GPSInfo] = gps_exif(latitude, longitude, altitude)
        name = f"walk/{index:03d}.jpg"
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        Image.new("RGB", (width, height), (index * 37 % 256, 255 - index * 11 % 256, 80)).save(folder / name, exif=exif)
        names.append(name)
    return names
