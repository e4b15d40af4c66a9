"""COLMAP models checked like kapture folders (`locretrieval.scene.colmap_files`): a binary file's
counts against its bytes before pycolmap reads it; cameras, names and poses after, binary and text;
a model as published ones are (a rig, distortion, thousands of keypoints) read as it is."""

from __future__ import annotations

import re
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from own_place import rig_model

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.errors import DataFileError
from locretrieval.scene.colmap import from_rigid3d, read_model

#: The first camera's record in cameras.bin: the count, then id, model id, width, height; its parameters after.
CAMERA_PARAMS = 8 + 24
#: The first frame's pose in frames.bin: the count, its id and rig id, then qw qx qy qz tx ty tz.
FRAME_POSE = 8 + 8


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("models")
    return {"binary": rig_model(root / "binary", keypoints=5000), "text": rig_model(root / "text", text=True)}


def copy(model: Path, folder: Path) -> Path:
    shutil.copytree(model, folder)
    return folder


def test_a_model_as_published_ones_are_reads_as_it_is(models):
    for model in models.values():
        reconstruction = read_model(model)
        assert reconstruction.num_reg_images() == 6 and reconstruction.num_points3D() == 20
        assert sorted(camera.model.name for camera in reconstruction.cameras.values()) == ["OPENCV", "SIMPLE_RADIAL"]
        centres = {image.name: image.projection_center() for image in reconstruction.images.values()}
        np.testing.assert_allclose(centres["cam2/002.jpg"], [-2.1, 0.0, 0.0])  # the rig's offset composed


def patched(path: Path, offset: int, layout: str, *values) -> None:
    data = bytearray(path.read_bytes())
    struct.pack_into(layout, data, offset, *values)
    path.write_bytes(bytes(data))


def points2d_count(data: bytes) -> tuple[bytes, str]:
    at = data.index(b"cam1/000.jpg\0") + 13  # the first image's number of 2D points, after its name
    left = len(data) - at - 8
    damaged = data[:at] + struct.pack("<Q", 2**50) + data[at + 8 :]
    return damaged, rf"image 1's 2D points declares 1125899906842624 entries of 24 bytes, but {left} bytes are left"


#: file -> how it is damaged: ``data -> (damaged data, the refusal)``.
DAMAGES = {
    "empty": ("points3D.bin", lambda data: (b"", r"cut short in the number of 3D points \(byte 0 of 0\)")),
    "truncated": (
        "points3D.bin",
        lambda data: (data[:-10], r"3D point 19 declares 6 entries of 8 bytes past the file's end"),
    ),
    "image count": (
        "images.bin",
        lambda data: (
            struct.pack("<Q", 2**40) + data[8:],
            rf"its header \(images\) declares 1099511627776 entries of 73 bytes, but {len(data) - 8} bytes are left",
        ),
    ),
    "2D point count": ("images.bin", points2d_count),
    "unterminated name": (
        "images.bin",
        lambda data: (
            data[: data.index(b"cam2/002.jpg") + 12],
            r"the name of image 6 has no terminating zero byte before the end of the file",
        ),
    ),
    "camera model": (
        "cameras.bin",
        lambda data: (
            data[:12] + struct.pack("<i", 99) + data[16:],
            r"camera 1 has a camera model id 99 that pycolmap does not know",
        ),
    ),
    "trailing": ("frames.bin", lambda data: (data + b"\0" * 5, r"5 bytes follow its last record")),
    "rig sensors": (
        "rigs.bin",
        lambda data: (
            data[:12] + struct.pack("<I", 10**9) + data[16:],
            rf"rig 1 declares 999999999 entries of 9 bytes, but {len(data) - 24} bytes are left",
        ),
    ),
}


@pytest.mark.parametrize("damage", sorted(DAMAGES))
def test_binary_counts_past_the_file_are_refused_before_pycolmap_reads_them(tmp_path, models, damage):
    """Each of these made pycolmap allocate what the count declared or read past the file's end
    (a 0-byte points3D.bin: 2.27 GB before a bad_alloc; an unterminated name: read forever)."""
    file, damaged = DAMAGES[damage]
    model = copy(models["binary"], tmp_path / "model")
    data, refusal = damaged((model / file).read_bytes())
    (model / file).write_bytes(data)
    with pytest.raises(DataFileError, match=rf"^{model / file}: {refusal}"):
        read_model(model)


#: A value each model file must not hold: (binary edit, text edit, refusal). pycolmap's text reader
#: itself refuses the tokens ``nan`` and ``inf`` (`PYCOLMAP_REFUSAL`, naming the folder); 1e300 it reads.
VALUES = {
    "focal 0": (
        ("cameras.bin", CAMERA_PARAMS, "<2d", 0.0, 0.0),
        ("cameras.txt", "1 OPENCV 64 48 50 51", "1 OPENCV 64 48 0 0"),
        r"camera 1: focal length\(s\) \[0\.0, 0\.0\] must be positive pixels",
    ),
    "negative focal": (
        ("cameras.bin", CAMERA_PARAMS + 8, "<d", -51.0),
        ("cameras.txt", "1 OPENCV 64 48 50 51", "1 OPENCV 64 48 50 -51"),
        r"camera 1: focal length\(s\) \[50\.0, -51\.0\] must be positive pixels",
    ),
    "nan parameter": (
        ("cameras.bin", CAMERA_PARAMS + 32, "<d", float("nan")),
        ("cameras.txt", "1 OPENCV 64 48 50 51 32 24 0.01", "1 OPENCV 64 48 50 51 32 24 nan"),
        r"camera 1: parameters \[50\.0, 51\.0, 32\.0, 24\.0, nan, .* must all be finite",
    ),
    "principal point": (
        ("cameras.bin", CAMERA_PARAMS + 16, "<d", 100.0),
        ("cameras.txt", "1 OPENCV 64 48 50 51 32", "1 OPENCV 64 48 50 51 100"),
        r"camera 1: principal point \(100\.0, 24\.0\) lies outside the 64 x 48 image",
    ),
    "nan quaternion": (
        ("frames.bin", FRAME_POSE, "<d", float("nan")),
        ("frames.txt", "1 1 1 0 0 0", "1 1 nan 0 0 0"),
        r"image 1 \('cam1/000\.jpg'\): pose quaternion \(wxyz\) \[nan, 0\.0, 0\.0, 0\.0\] is not",
    ),
    "zero quaternion": (
        ("frames.bin", FRAME_POSE, "<d", 0.0),
        ("frames.txt", "1 1 1 0 0 0", "1 1 0 0 0 0"),
        r"image 1 .*: pose quaternion \(wxyz\) \[0\.0, 0\.0, 0\.0, 0\.0\] is not a finite unit quaternion \(norm 0,",
    ),
    "norm 2": (
        ("frames.bin", FRAME_POSE, "<d", 2.0),
        ("frames.txt", "1 1 1 0 0 0", "1 1 2 0 0 0"),
        r"image 1 .*: pose quaternion \(wxyz\) \[2\.0, 0\.0, 0\.0, 0\.0\] is not a finite unit quaternion \(norm 2, "
        r"tolerance 0\.001\)",
    ),
    "overflowing quaternion": (
        ("frames.bin", FRAME_POSE, "<2d", 1e300, 1e300),
        ("frames.txt", "1 1 1 0 0 0", "1 1 1e300 1e300 0 0"),
        r"image 1 .*: pose quaternion \(wxyz\) \[1e\+300, 1e\+300, 0\.0, 0\.0\] is not a finite unit quaternion "
        r"\(norm inf,",
    ),
    "infinite translation": (
        ("frames.bin", FRAME_POSE + 32, "<d", float("inf")),
        ("frames.txt", "1 1 1 0 0 0 0", "1 1 1 0 0 0 inf"),
        r"image 1 \('cam1/000\.jpg'\): pose translation \[inf, 0\.0, 0\.0\] is not finite",
    ),
}
PYCOLMAP_REFUSAL = "pycolmap cannot read this COLMAP model"


@pytest.mark.parametrize("kind", ["binary", "text"])
@pytest.mark.parametrize("case", sorted(VALUES))
def test_cameras_and_poses_that_lie_are_refused_naming_file_and_id(tmp_path, models, kind, case):
    binary, (file, written, lie), refusal = VALUES[case]
    model = copy(models[kind], tmp_path / "model")
    if kind == "binary":
        path = model / binary[0]
        patched(path, *binary[1:])
    else:
        path = model / file
        content, count = re.subn(rf"^{re.escape(written)}\b", lie, path.read_text(), count=1, flags=re.M)
        assert count == 1
        path.write_text(content)
        if re.search(r"\b(nan|inf)\b", lie):
            path, refusal = model, PYCOLMAP_REFUSAL
    with pytest.raises(DataFileError, match=rf"^{path}: {refusal}"):
        read_model(model)


@pytest.mark.parametrize("kind", ["binary", "text"])
def test_a_name_that_is_not_utf8_is_refused_naming_the_image_id(tmp_path, models, kind):
    model = copy(models[kind], tmp_path / "model")
    path = model / ("images.bin" if kind == "binary" else "images.txt")
    path.write_bytes(path.read_bytes().replace(b"cam1/000.jpg", b"cam1/\xe9\xe9\xe9.jpg"))
    with pytest.raises(DataFileError, match=rf"^{path}: image 1: its name is not UTF-8 text \(invalid continuation"):
        read_model(model)


def test_a_quaternion_within_the_tolerance_is_normalised(tmp_path, models):
    model = copy(models["binary"], tmp_path / "model")
    patched(model / "frames.bin", FRAME_POSE, "<d", 1.0005)  # |q| = 1.0005: written to 4 digits
    image = read_model(model).image(1)
    assert image.cam_from_world().rotation.quat[3] == 1.0005
    qvec, _ = from_rigid3d(image.cam_from_world())
    np.testing.assert_allclose(qvec, [1.0, 0.0, 0.0, 0.0])
