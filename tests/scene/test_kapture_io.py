"""Kapture folders written with the kapture library, read back with locretrieval; LTVL export."""

from __future__ import annotations

from pathlib import Path

import kapture
import numpy as np
import pytest
from kapture_folders import PINHOLE, SIMPLE_RADIAL, pose, write_kapture
from PIL import Image

from locretrieval import geometry
from locretrieval.scene import Camera, kapture_io
from locretrieval.scene.kapture_io import KaptureFormatError, load_image_set, load_kapture_scene
from locretrieval.scene.ltvl import FileNames, KaptureNames, WithoutFirstFolder, write_ltvl


@pytest.fixture
def mapping(tmp_path):
    """A rig of two cameras (PINHOLE, SIMPLE_RADIAL) posed per rig, plus a camera posed on its
    own; a depth map, tags.txt and a mask. Returns the folder and the expected 4x4 poses."""
    cam0_from_rig, T_cam0_rig = pose("y", 90.0, [0.5, 0.0, 0.0])
    cam1_from_rig, T_cam1_rig = pose("y", -90.0, [-0.5, 0.0, 0.1])
    rig_t0, T_rig_t0 = pose("z", 30.0, [1.0, 2.0, 3.0])
    rig_t1, T_rig_t1 = pose("x", -45.0, [-4.0, 0.5, 2.0])
    phone, T_phone = pose("z", 120.0, [0.0, -1.0, 7.0])
    root = write_kapture(
        tmp_path / "mapping",
        sensors={
            "cam0": PINHOLE,
            "cam1": SIMPLE_RADIAL,
            "phone": PINHOLE,
            "cam0_depth": kapture.Camera(
                kapture.CameraType.PINHOLE, [40, 30, 35.0, 36.0, 20.0, 15.0], sensor_type="depth"
            ),
        },
        records={
            (0, "cam0"): "rig/cam0/000.png",
            (0, "cam1"): "rig/cam1/000.png",
            (1, "cam0"): "rig/cam0/001.png",
            (1, "cam1"): "rig/cam1/001.png",
            (5, "phone"): "phone/005.png",
        },
        trajectories={(0, "rig"): rig_t0, (1, "rig"): rig_t1, (5, "phone"): phone},
        rigs={("rig", "cam0"): cam0_from_rig, ("rig", "cam1"): cam1_from_rig},
        depth={(0, "cam0_depth"): "rig/cam0/000.depth"},
    )
    (root / "tags.txt").write_text("# image_name, tags\nrig/cam1/001.png, blur dynamic\nphone/005.png, handheld\n")
    (root / "masks" / "rig" / "cam0").mkdir(parents=True)
    Image.fromarray(np.zeros((30, 40), np.uint8)).save(root / "masks" / "rig" / "cam0" / "001.png")
    expected = {
        "rig/cam0/000.png": T_cam0_rig @ T_rig_t0,
        "rig/cam1/000.png": T_cam1_rig @ T_rig_t0,
        "rig/cam0/001.png": T_cam0_rig @ T_rig_t1,
        "rig/cam1/001.png": T_cam1_rig @ T_rig_t1,
        "phone/005.png": T_phone,
    }
    return root, expected


def query_folder(tmp_path: Path, name: str, images: dict[tuple[int, str], str], trajectories=None) -> Path:
    return write_kapture(tmp_path / name, {"phone": PINHOLE}, images, trajectories)


def assert_poses(image_set, expected: dict[str, np.ndarray]) -> None:
    for i, name in enumerate(image_set.names):
        T = expected[name]
        np.testing.assert_allclose(geometry.quaternion_to_matrix(image_set.qvec[i]), T[:3, :3], atol=1e-12)
        np.testing.assert_allclose(image_set.tvec[i], T[:3, 3], atol=1e-12)
        np.testing.assert_allclose(image_set.centers[i], -T[:3, :3].T @ T[:3, 3], atol=1e-12)


def test_mapping_folder_round_trip(mapping):
    root, expected = mapping
    images = load_image_set(root, tag="mapping")
    assert images.names == [
        "rig/cam0/000.png",
        "rig/cam1/000.png",
        "rig/cam0/001.png",
        "rig/cam1/001.png",
        "phone/005.png",
    ]
    assert images.image_root == root / "sensors" / "records_data"
    assert all(path.is_file() for path in images.paths)
    assert images.cameras[0] == Camera("PINHOLE", 40, 30, (35.0, 36.0, 20.0, 15.0))
    assert images.cameras[1] == Camera("SIMPLE_RADIAL", 32, 24, (30.0, 16.0, 12.0, 0.01))
    assert images.has_pose.all()
    assert_poses(images, expected)
    assert images.tags[0] == {"mapping"}
    assert images.tags[3] == {"mapping", "blur", "dynamic"}
    assert images.tags[4] == {"mapping", "handheld"}
    assert images.depth_paths == [images.image_root / "rig/cam0/000.depth", None, None, None, None]
    assert images.mask_paths == [None, None, root / "masks/rig/cam0/001.png", None, None]


def test_each_file_is_parsed_once_by_the_checked_reader(mapping, monkeypatch):
    """kapture's CSV readers (which skip or crash on bad lines) are not run after the checked pass;
    every file the folder holds is read once, and the poses are the same."""
    root, expected = mapping
    reads = []
    original = kapture_io.read_csv_rows
    monkeypatch.setattr(kapture_io, "read_csv_rows", lambda path, *a: reads.append(path.name) or original(path, *a))
    for reader in ("sensors_from_file", "rigs_from_file", "trajectories_from_file", "records_camera_from_file"):
        monkeypatch.setattr(kapture.io.csv, reader, lambda *a, **k: pytest.fail("kapture's reader parsed a file again"))
    images = load_image_set(root)
    assert_poses(images, expected)
    assert sorted(reads) == sorted(
        ["sensors.txt", "rigs.txt", "records_camera.txt", "trajectories.txt", "records_depth.txt"]
    )


def test_pose_of_rig_camera_recovered_from_its_sibling(tmp_path):
    """RobotCar Seasons v2 gives only the rear camera's pose for its new training images."""
    rear_from_rig, T_rear_rig = pose("y", 180.0, [0.0, 0.2, -1.0])
    left_from_rig, T_left_rig = pose("y", -90.0, [0.5, 0.2, 0.0])
    rear_from_world, T_rear_world = pose("x", 20.0, [3.0, -2.0, 1.0])
    root = write_kapture(
        tmp_path / "robotcar",
        {"rear": PINHOLE, "left": PINHOLE},
        {(7, "rear"): "sun/rear/7.png", (7, "left"): "sun/left/7.png"},
        {(7, "rear"): rear_from_world},
        {("car", "rear"): rear_from_rig, ("car", "left"): left_from_rig},
    )
    images = load_image_set(root)
    expected = {"sun/rear/7.png": T_rear_world, "sun/left/7.png": T_left_rig @ np.linalg.inv(T_rear_rig) @ T_rear_world}
    assert_poses(images, expected)


def test_folder_without_trajectories_has_nan_poses_and_no_side_files(tmp_path):
    root = query_folder(tmp_path, "query_night", {(3, "phone"): "night/a.png", (4, "phone"): "night/b.png"})
    images = load_image_set(root, tag="night")
    assert not images.has_pose.any()
    assert np.isnan(images.qvec).all() and np.isnan(images.tvec).all()
    assert images.tags == [frozenset({"night"})] * 2
    assert images.depth_paths is None and images.mask_paths is None


def test_scene_from_mapping_and_two_query_folders(tmp_path, mapping):
    mapping_root, expected = mapping
    day_pose, T_day = pose("z", -10.0, [1.0, 1.0, 1.0])
    day = query_folder(
        tmp_path, "query_day", {(1, "phone"): "day/a.png", (2, "phone"): "day/b.png"}, {(2, "phone"): day_pose}
    )
    night = query_folder(tmp_path, "query_night", {(1, "phone"): "night/a.png"})
    scene = load_kapture_scene("toy", mapping_root, [day, night])
    assert scene.database.names == list(expected)
    assert scene.queries.names == ["day/a.png", "day/b.png", "night/a.png"]
    assert scene.queries.tags == [frozenset({"query_day"})] * 2 + [frozenset({"query_night"})]
    assert scene.queries.has_pose.tolist() == [False, True, False]
    assert_poses(scene.queries.subset(np.array([1])), {"day/b.png": T_day})
    assert scene.queries.paths == [
        day / "sensors/records_data/day/a.png",
        day / "sensors/records_data/day/b.png",
        night / "sensors/records_data/night/a.png",
    ]
    assert scene.queries.image_root == tmp_path
    assert scene.sources == [mapping_root, day, night]
    tagged = load_kapture_scene(
        "toy", mapping_root, [day, night], query_tags=["day", "night"], name_tags={"cam0": "/cam0/"}
    )
    assert tagged.queries.tags == [frozenset({"day"})] * 2 + [frozenset({"night"})]
    assert tagged.database.tag_mask("cam0").tolist() == [True, False, True, False, False]


def test_duplicate_names_across_query_folders_are_an_error(tmp_path, mapping):
    first = query_folder(tmp_path, "query_a", {(1, "phone"): "same.png"})
    second = query_folder(tmp_path, "query_b", {(9, "phone"): "same.png"})
    with pytest.raises(ValueError, match=r"'same.png' is in both .*query_a.* and .*query_b"):
        load_kapture_scene("toy", mapping[0], [first, second])


def test_unposed_mapping_images_are_left_out_of_the_database(tmp_path, mapping, caplog):
    posed, _ = pose("z", 5.0, [0.0, 0.0, 1.0])
    root = write_kapture(
        tmp_path / "map", {"phone": PINHOLE}, {(1, "phone"): "a.png", (2, "phone"): "b.png"}, {(1, "phone"): posed}
    )
    scene = load_kapture_scene("toy", root, [mapping[0]])
    assert scene.database.names == ["a.png"]
    assert "1 of 2 mapping images" in caplog.text and "b.png" in caplog.text


def append_line(path: Path, line: str) -> int:
    """Append ``line`` to a text file; returns its line number."""
    text = path.read_text()
    path.write_text(text + ("" if text.endswith("\n") else "\n") + line + "\n")
    return len(path.read_text().splitlines())


BAD_LINES = [
    ("sensors/trajectories.txt", "9, phone, 1, 0, 0, 0, 1, 2", "expected 9 comma-separated fields, got 8"),
    ("sensors/trajectories.txt", "9, phone, 1, 0, 0, zero, 1, 2, 3", "non-numeric quaternion"),
    ("sensors/trajectories.txt", "9, phone, nan, 0, 0, 0, 1, 2, 3", "not a finite unit quaternion"),
    ("sensors/trajectories.txt", "9, phone, 0.9, 0, 0, 0, 1, 2, 3", "not a finite unit quaternion (norm 0.9"),
    ("sensors/trajectories.txt", "9, ghost, 1, 0, 0, 0, 1, 2, 3", "trajectory for unknown sensor or rig 'ghost'"),
    ("sensors/trajectories.txt", "1.5, phone, 1, 0, 0, 0, 1, 2, 3", "timestamp '1.5' is not an integer"),
    (
        "sensors/trajectories.txt",
        "1, phone, 1, 0, 0, 0, 1, 2, 3",
        "duplicate (timestamp, device) (1, 'phone'): also on line",
    ),
    # kapture parses 01 as 1: the same pose line twice, not two poses (defect 3 of the hostile-input issue)
    (
        "sensors/trajectories.txt",
        "01, phone, 1, 0, 0, 0, 1, 2, 3",
        "duplicate (timestamp, device) (1, 'phone'): also on line",
    ),
    ("sensors/records_camera.txt", "001, phone, b.png", "duplicate (timestamp, sensor) (1, 'phone'): also on line"),
    ("sensors/records_camera.txt", "9, phone", "expected 3 comma-separated fields, got 2"),
    ("sensors/records_camera.txt", "x9, phone, x.png", "timestamp 'x9' is not an integer"),
    ("sensors/records_camera.txt", "9, ghost, x.png", "record of unknown sensor 'ghost'"),
    (
        "sensors/sensors.txt",
        "fish, , camera, FISHEYE_9, 4, 3, 1, 2, 2",
        "sensor 'fish': unknown camera model 'FISHEYE_9'",
    ),
    ("sensors/sensors.txt", "cam, , camera, PINHOLE, 4, 3, 1, 1, 2", "camera model PINHOLE takes 6 values"),
    ("sensors/sensors.txt", "cam, , camera, PINHOLE, 4, 3, f, 1, 2, 2", "non-numeric camera parameters"),
    ("tags.txt", "ghost.png, day", "image 'ghost.png' is not in sensors/records_camera.txt"),
    ("tags.txt", "no-comma-here", "expected 'image_name, tag1 tag2 ...'"),
]


@pytest.mark.parametrize(("relative", "line", "problem"), BAD_LINES)
def test_bad_lines_name_file_line_and_content(tmp_path, relative, line, problem):
    start, _ = pose("z", 1.0, [0.0, 0.0, 0.0])
    root = query_folder(tmp_path, "folder", {(1, "phone"): "a.png"}, {(1, "phone"): start})
    (root / "tags.txt").write_text("# image_name, tags\na.png, day\n")
    number = append_line(root / relative, line)
    with pytest.raises(KaptureFormatError) as error:
        load_image_set(root)
    message = str(error.value)
    assert f"{root / relative}:{number}:" in message
    assert problem in message
    assert repr(line) in message


def test_unusable_camera_models_name_file_line_and_sensor(tmp_path):
    root = query_folder(tmp_path, "folder", {(1, "phone"): "a.png"})
    text = (root / "sensors/sensors.txt").read_text()
    (root / "sensors/sensors.txt").write_text(text.replace("PINHOLE, 40, 30, 35, 36, 20, 15", "UNKNOWN_CAMERA, 40, 30"))
    number = next(
        i
        for i, line in enumerate((root / "sensors/sensors.txt").read_text().splitlines(), 1)
        if "UNKNOWN_CAMERA" in line
    )
    with pytest.raises(
        KaptureFormatError,
        match=rf"sensors.txt:{number}: camera 'phone' has model UNKNOWN_CAMERA, which locretrieval cannot use",
    ):
        load_image_set(root)


def test_missing_image_names_file_and_folder(tmp_path):
    root = query_folder(tmp_path, "folder", {(1, "phone"): "a.png", (2, "phone"): "sub/b.png"})
    (root / "sensors/records_data/sub/b.png").unlink()
    with pytest.raises(
        FileNotFoundError,
        match=r"1 image file\(s\) .* missing from .*folder/sensors/records_data, e.g. \['sub/b.png'\]",
    ):
        load_image_set(root)


def test_not_a_kapture_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"not a kapture folder: .*empty/sensors/sensors.txt is missing"):
        load_image_set(tmp_path / "empty")


def test_rig_with_non_unit_quaternion_names_line(tmp_path, mapping):
    root, _ = mapping
    number = append_line(root / "sensors/rigs.txt", "rig, phone, 2, 0, 0, 0, 0, 0, 0")
    with pytest.raises(
        KaptureFormatError, match=rf"rigs.txt:{number}: quaternion .* not a finite unit quaternion \(norm 2"
    ):
        load_image_set(root)


def test_ltvl_export(tmp_path):
    names = ["query/day/milestone/IMG_1.jpg", "night-rain/rear/1417.jpg", "query/night/nexus5x/IMG_2.jpg"]
    qvec = np.array([[1.0, 0.0, 0.0, 0.0], [np.nan] * 4, [0.5, 0.5, -0.5, 0.5]])
    tvec = np.array([[1.5, -2.0, 3.25], [0.0, 0.0, 0.0], [0.1, 1e-5, -7.0]])
    path = tmp_path / "ltvl" / "aachen.txt"
    assert write_ltvl(path, names, qvec, tvec, FileNames()) == 1
    assert path.read_text() == "IMG_1.jpg 1.0 0.0 0.0 0.0 1.5 -2.0 3.25\nIMG_2.jpg 0.5 0.5 -0.5 0.5 0.1 1e-05 -7.0\n"
    assert write_ltvl(path, names, qvec, tvec, KaptureNames()) == 1
    assert path.read_text().splitlines()[1].startswith("query/night/nexus5x/IMG_2.jpg 0.5 ")
    assert write_ltvl(path, names[1:2], qvec[[0]], tvec[[0]], WithoutFirstFolder()) == 0
    assert path.read_text() == "rear/1417.jpg 1.0 0.0 0.0 0.0 1.5 -2.0 3.25\n"
    assert [names("a/b/c.jpg") for names in (KaptureNames(), FileNames(), WithoutFirstFolder())] == [
        "a/b/c.jpg",
        "c.jpg",
        "b/c.jpg",
    ]


def test_ltvl_export_rejects_ambiguous_or_unwritable_names(tmp_path):
    q, t = np.array([[1.0, 0, 0, 0]] * 2), np.zeros((2, 3))
    with pytest.raises(ValueError, match="same name, e.g. \\['x.jpg'\\]"):
        write_ltvl(tmp_path / "a.txt", ["day/x.jpg", "night/x.jpg"], q, t, FileNames())
    with pytest.raises(ValueError, match="no leading folder"):
        write_ltvl(tmp_path / "a.txt", ["x.jpg", "y.jpg"], q, t, WithoutFirstFolder())
    with pytest.raises(ValueError, match="whitespace"):
        write_ltvl(tmp_path / "a.txt", ["x y.jpg", "z.jpg"], q, t, KaptureNames())
    assert not (tmp_path / "a.txt").exists()


def write_text_folder(root: Path, files: dict[str, str], images: dict[str, tuple[int, int]]) -> Path:
    """A kapture folder written as text, line by line as NAVER's published datasets are (not by
    the kapture library), with gray PNG images of the given (width, height)."""
    for relative, text in files.items():
        (root / relative).parent.mkdir(parents=True, exist_ok=True)
        (root / relative).write_text(text)
    for name, (width, height) in images.items():
        path = root / "sensors" / "records_data" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(np.full((height, width, 3), 128, np.uint8)).save(path)
    return root


HEADER = "# kapture format: 1.1\n"


def test_published_layout_with_sensorless_rig_members_and_unused_records_loads_with_warnings(tmp_path, caplog):
    # a rig describing more cameras than the recording uses (no sensors.txt line for cam_right),
    # a lidar member, gnss/lidar sensors and records, a depth record whose file was not downloaded
    cam_from_rig, T_cam_rig = pose("y", 90.0, [0.5, 0.0, 0.0])
    rig_from_world, T_rig_world = pose("z", 30.0, [1.0, 2.0, 3.0])
    q, t = cam_from_rig.r_raw, cam_from_rig.t_raw
    rq, rt = rig_from_world.r_raw, rig_from_world.t_raw
    mapping = write_text_folder(
        tmp_path / "mapping",
        {
            "sensors/sensors.txt": HEADER + "# sensor_device_id, name, sensor_type, [sensor_params]+\n"
            "cam_left, left, camera, SIMPLE_RADIAL, 32, 24, 30.0, 16.0, 12.0, 0.01\n"
            "gps0, , gnss, EPSG:4326\nvelodyne, , lidar\nthermo, , thermometer\n",
            "sensors/rigs.txt": HEADER + "# rig_device_id, sensor_device_id, qw, qx, qy, qz, tx, ty, tz\n"
            f"car, cam_left, {', '.join(map(str, q))}, {', '.join(map(str, t))}\n"
            "car, cam_right, 1, 0, 0, 0, -0.5, 0, 0\ncar, velodyne, 1, 0, 0, 0, 0, 0, 1.2\n",
            "sensors/trajectories.txt": HEADER + "# timestamp, device_id, qw, qx, qy, qz, tx, ty, tz\n"
            f"100, car, {', '.join(map(str, rq))}, {', '.join(map(str, rt))}\n",
            "sensors/records_camera.txt": HEADER + "# timestamp, device_id, image_path\n100, cam_left, left/100.jpg\n",
            "sensors/records_gnss.txt": HEADER
            + "# timestamp, device_id, x, y, z, utc, dop\n100, gps0, 2.3, 48.8, 35.0, 0, 1.0\n",
            "sensors/records_lidar.txt": HEADER
            + "# timestamp, device_id, point_cloud_path\n100, velodyne, velodyne/100.pcd\n",
            "sensors/records_depth.txt": HEADER
            + "# timestamp, device_id, depth_map_path\n100, cam_left_depth, left/100.depth\n",
        },
        {"left/100.jpg": (32, 24)},
    )
    query = write_text_folder(
        tmp_path / "query",
        {
            "sensors/sensors.txt": HEADER + "q_left, , camera, SIMPLE_RADIAL, 32, 24, 30.0, 16.0, 12.0, 0.01\n",
            "sensors/rigs.txt": HEADER + "q_car, q_left, 1, 0, 0, 0, 0, 0, 0\nq_car, q_right, 1, 0, 0, 0, -0.5, 0, 0\n",
            "sensors/records_camera.txt": HEADER + "7, q_left, query/7.jpg\n",
        },
        {"query/7.jpg": (32, 24)},
    )
    scene = load_kapture_scene("published", [mapping], [query])
    assert scene.database.names == ["left/100.jpg"] and scene.queries.names == ["query/7.jpg"]
    assert_poses(scene.database, {"left/100.jpg": T_cam_rig @ T_rig_world})
    assert scene.database.depth_paths is None and not scene.queries.has_pose.any()
    warnings = caplog.text
    assert "rigs.txt: 1 rig member(s) without a line in sensors/sensors.txt, unused: ['car/cam_right']" in warnings
    assert "unused: ['q_car/q_right']" in warnings
    assert "sensor types unknown to kapture, not used by the benchmark: ['thermometer']" in warnings
    assert "records not used by the benchmark: ['records_gnss.txt', 'records_lidar.txt']" in warnings
    assert f"{mapping / 'sensors/records_depth.txt'}: 1 depth record(s) left out" in warnings
