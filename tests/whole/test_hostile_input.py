"""Hostile and sloppy input: every bad value stops with an error naming the file (or key) and
what was wrong, no code runs from a data file, nothing is silently wrong. Tiny folders only."""

import re
from pathlib import Path

import helpers
import numpy as np
import pytest

from locretrieval.report.markdown import md_text
from locretrieval.scene import Camera, ImageSet
from locretrieval.scene.feature_files import read_feature_array, read_feature_header
from locretrieval.scene.kapture_io import KaptureFormatError
from locretrieval.sfm.features import extract_features

NAMES = ["cam/a.jpg", "cam/b.jpg"]


def image_set(root: Path, names: list[str] = NAMES) -> ImageSet:
    camera = Camera("PINHOLE", 64, 48, (50.0, 50.0, 32.0, 24.0))
    return ImageSet(
        names, root, [camera] * len(names), np.tile([1.0, 0, 0, 0], (len(names), 1)), np.zeros((len(names), 3))
    )


def write_global_features(kapture_dir: Path, dtype_field: str, vectors: np.ndarray, dsize: int) -> Path:
    """A global-features folder whose header says ``dtype_field`` (raw bytes of ``vectors``)."""
    folder = kapture_dir / "reconstruction" / "global_features" / "feats"
    folder.mkdir(parents=True)
    (folder / "global_features.txt").write_text(
        f"# name, dtype, dsize, metric_type\nfeats, {dtype_field}, {dsize}, L2\n"
    )
    for name, vector in zip(NAMES, vectors):
        path = folder / f"{name}.gfeat"
        path.parent.mkdir(parents=True, exist_ok=True)
        vector.tofile(path)
    return folder


def write_local_features(kapture_dir: Path, keypoints_dtype: str, descriptors_dtype: str) -> None:
    rng = np.random.default_rng(0)
    for kind, header, rows in (
        ("keypoints", f"r2d2, {keypoints_dtype}, 3", rng.uniform(0, 40, (5, 3)).astype(np.float32)),
        ("descriptors", f"r2d2, {descriptors_dtype}, 8, r2d2, L2", rng.normal(size=(5, 8)).astype(np.float32)),
    ):
        folder = kapture_dir / "reconstruction" / kind / "r2d2"
        folder.mkdir(parents=True)
        (folder / f"{kind}.txt").write_text(f"# header\n{header}\n")
        for name in NAMES:
            path = folder / f"{name}.{'kpt' if kind == 'keypoints' else 'desc'}"
            path.parent.mkdir(parents=True, exist_ok=True)
            rows.tofile(path)


def command_dtype(marker: Path) -> str:
    """A header dtype field that, if evaluated, creates ``marker``."""
    return f"__import__('os').system('touch {marker}')"


# --------------------------------------------------------------- 1. no code runs from a data file


def test_global_features_header_is_parsed_not_evaluated(tmp_path):
    marker = tmp_path / "pwned"
    vectors = np.eye(2, 4, dtype=np.float32)
    folder = write_global_features(tmp_path / "mapping", command_dtype(marker), vectors, 4)
    with pytest.raises(KaptureFormatError, match=r"global_features\.txt:2: dtype .*__import__.* is not one of"):
        helpers.precomputed(path=folder)
    assert not marker.exists()


def test_local_feature_headers_are_parsed_not_evaluated(tmp_path):
    marker = tmp_path / "pwned"
    root = tmp_path / "mapping"
    write_local_features(root, command_dtype(marker), "float32")
    config = helpers.sfm_settings({"features": {"name": "r2d2"}}, choices=["sfm/features=kapture"]).features
    images = image_set(root / "sensors" / "records_data")
    with pytest.raises(KaptureFormatError, match=r"keypoints\.txt:2: dtype .*__import__"):
        extract_features(images, config, tmp_path / "cache", workers=1)
    assert not marker.exists()
    (root / "reconstruction" / "keypoints" / "r2d2" / "keypoints.txt").write_text("r2d2, float32, 3\n")
    (root / "reconstruction" / "descriptors" / "r2d2" / "descriptors.txt").write_text(
        f"r2d2, {command_dtype(marker)}, 8, r2d2, L2\n"
    )
    with pytest.raises(KaptureFormatError, match=r"descriptors\.txt:1: dtype"):
        extract_features(images, config, tmp_path / "cache", workers=1)
    assert not marker.exists()


@pytest.mark.parametrize("field", ["float32", "np.float32", "numpy.float32"])
def test_dtype_spellings_kapture_writes_are_accepted(tmp_path, field):
    vectors = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 2.0]], dtype=np.float32)
    folder = write_global_features(tmp_path / "mapping", field, vectors, 3)
    header = read_feature_header(folder / "global_features.txt", "global_features")
    assert (header.name, header.dtype, header.dsize, header.metric_type) == ("feats", np.float32, 3, "L2")
    np.testing.assert_array_equal(read_feature_array(folder / "cam/a.jpg.gfeat", header), vectors[:1])


# --------------------------------------------- 5. a same-width dtype is not reinterpreted silently


def test_integer_global_features_are_refused_unless_allowed(tmp_path):
    vectors = np.array([[3.0, 4.0], [1.0, 0.0]], dtype=np.float32)
    folder = write_global_features(tmp_path / "mapping", "int32", vectors, 2)  # same width as the float32 data
    with pytest.raises(
        ValueError, match=r"global_features\.txt: dtype int32 is not floating point.*allow_integer=true"
    ):
        helpers.precomputed(path=folder)
    model = helpers.precomputed(path=folder, allow_integer=True)
    assert model.describe(image_set(tmp_path / "mapping" / "sensors" / "records_data")).dtype == np.float32


def test_local_feature_file_of_the_wrong_size_names_file_and_row_size(tmp_path):
    root = tmp_path / "mapping"
    write_local_features(root, "float32", "float32")
    descriptors = root / "reconstruction" / "descriptors" / "r2d2" / "cam" / "b.jpg.desc"
    descriptors.write_bytes(descriptors.read_bytes()[:-4])
    config = helpers.sfm_settings({"features": {"name": "r2d2"}}, choices=["sfm/features=kapture"]).features
    with pytest.raises(
        ValueError, match=r"b\.jpg\.desc: 156 bytes is not a whole number of descriptors rows of 8 x float32"
    ):
        extract_features(image_set(root / "sensors" / "records_data"), config, tmp_path / "cache", workers=1)


# ------------------------------------ 2. an image of another size than its camera is an error


def phone_folder(tmp_path: Path, names: dict[tuple[int, str], str]) -> Path:
    from kapture_folders import PINHOLE, pose, write_kapture

    start, _ = pose("z", 1.0, [0.0, 0.0, 0.0])
    return write_kapture(tmp_path / "query", {"phone": PINHOLE}, names, {key: start for key in names})


def test_an_image_resized_behind_its_camera_names_both_sizes(tmp_path):
    from PIL import Image

    from locretrieval.scene.kapture_io import load_image_set

    root = phone_folder(tmp_path, {(1, "phone"): "a.png", (2, "phone"): "b.png"})
    image = root / "sensors" / "records_data" / "b.png"
    width, height = Image.open(image).size
    Image.new("RGB", (2 * width, 2 * height)).save(image)
    with pytest.raises(
        ValueError,
        match=rf"b\.png: image is {2 * width}x{2 * height} pixels but its camera 'phone' .* is {width}x{height}",
    ):
        load_image_set(root)


# ----------------------------- 3. timestamps are compared as the integers kapture reads


def test_a_timestamp_written_twice_in_two_spellings_names_both_lines(tmp_path):
    from locretrieval.scene.kapture_io import load_image_set

    root = phone_folder(tmp_path, {(2, "phone"): "a.png"})
    with (root / "sensors" / "trajectories.txt").open("a") as stream:
        stream.write("02, phone, 1, 0, 0, 0, 5, 5, 5\n")
    with pytest.raises(
        KaptureFormatError,
        match=r"trajectories\.txt:\d+: duplicate \(timestamp, device\) \(2, 'phone'\): also on line \d+",
    ):
        load_image_set(root)


# --------------------------------------- 8. failures that used to come after all the work


def test_image_names_with_whitespace_are_refused_when_the_scene_loads(tmp_path):
    from locretrieval.scene.kapture_io import load_image_set

    root = phone_folder(tmp_path, {(1, "phone"): "my photo.png"})
    with pytest.raises(ValueError, match=r"records_camera\.txt: image names with whitespace .*'my photo\.png'"):
        load_image_set(root)


# ---------------------------------------------------------------- 7. every error names the file


@pytest.mark.parametrize("content", [np.random.default_rng(0).bytes(300), __import__("pickle").dumps({"net": [1, 2]})])
def test_a_netvlad_file_that_is_not_a_mat_struct_names_the_file(tmp_path, content):
    path = tmp_path / "Pitts30K_struct.mat"
    path.write_bytes(content)
    with pytest.raises(
        ValueError, match=r"Pitts30K_struct\.mat: not a MATLAB \.mat file holding NetVLAD's struct 'net'"
    ):
        helpers.zoo_model("netvlad", weights=path)


def test_an_unwritable_cache_names_the_file_it_could_not_write(tmp_path):
    from locretrieval.cache import save_arrays

    blocked = tmp_path / "cache"
    blocked.write_text("a file where the cache folder should be")
    with pytest.raises(OSError, match=r"cannot write .*cache/descriptors/x\.npz .*is the cache folder writable"):
        save_arrays(blocked / "descriptors" / "x.npz", {"a": np.zeros(2)})


# ------------------------------------------------- 4. workers never outlive the run that started them


def test_workers_exit_when_their_parent_dies_while_they_start(tmp_path):
    import os
    import subprocess
    import sys
    import time

    script = (
        "import os\n"
        "from locretrieval.pool import WORKERS\n"
        "pool = WORKERS.executor(2)\n"
        "pool.submit(os.getpid)\n"
        "pool.submit(os.getpid)\n"
        "print(' '.join(str(pid) for pid in pool._processes), flush=True)\n"  # loky's workers, by pid
        "os._exit(0)\n"  # the parent dies while its workers import torch and pycolmap
    )
    pids = tmp_path / "workers.txt"
    with pids.open("w") as stream:  # a file, not a pipe: the workers inherit it
        subprocess.run([sys.executable, "-c", script], stdout=stream, timeout=120, check=True)
    workers = [int(pid) for pid in pids.read_text().split()]
    assert len(workers) == 2

    def alive(pid: int) -> bool:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
        except FileNotFoundError:
            return False
        return state not in ("Z", "X")

    try:
        deadline = time.monotonic() + 60
        while any(alive(pid) for pid in workers) and time.monotonic() < deadline:
            time.sleep(0.5)
        assert not any(alive(pid) for pid in workers)
    finally:  # never leave a stray process behind
        for pid in filter(alive, workers):
            os.kill(pid, 9)


# --------------------------------------------------- 6. values of the wrong range name where they are


def test_a_negative_focal_length_names_the_sensor_line(tmp_path):
    import kapture
    from kapture_folders import write_kapture

    from locretrieval.scene.kapture_io import load_image_set

    camera = kapture.Camera(kapture.CameraType.PINHOLE, [64, 48, -50.0, 50.0, 32.0, 24.0])
    root = write_kapture(tmp_path / "query", {"phone": camera}, {(1, "phone"): "a.png"})
    with pytest.raises(
        KaptureFormatError,
        match=r"sensors\.txt:\d+: camera 'phone': focal length\(s\) \[-50\.0, 50\.0\] must be positive",
    ):
        load_image_set(root)


# ========================================================= third pass (#49): crafted datasets and names


def files_below(folder: Path) -> set[Path]:
    return {path for path in folder.rglob("*") if path.is_file()}


@pytest.mark.slow
def test_a_hostile_run_writes_only_in_its_run_and_cache_folders(hostile_run):
    from helpers import HOSTILE_MODEL

    outside = {
        path
        for path in files_below(hostile_run.root)
        if not path.is_relative_to(hostile_run.run)
        and not path.is_relative_to(hostile_run.cache)
        and path.parts[len(hostile_run.root.parts)] not in ("render", "data")  # the dataset
    }
    assert outside == set()  # model.name=../../../x wrote x.npz and x/*.txt three levels up
    rankings = sorted(path.name for path in (hostile_run.run / "rankings").iterdir())
    assert len(rankings) >= 2 and all(re.fullmatch(r"[A-Za-z0-9_.-]+\.npz", name) for name in rankings)
    stored = {str(np.load(path)["name"]) for path in (hostile_run.run / "rankings").iterdir()}
    assert HOSTILE_MODEL in stored
    assert all(path.parent.parent == hostile_run.run / "ltvl" for path in (hostile_run.run / "ltvl").rglob("*.txt"))


def report_markup(page: str) -> tuple[set[str], list[tuple[str, str]]]:
    """The tag names of an HTML page and its ``(tag, attribute)`` pairs."""
    from html.parser import HTMLParser

    tags, attributes = set(), []

    class Collector(HTMLParser):
        def handle_starttag(self, tag, attrs):
            tags.add(tag)
            attributes.extend((tag, name) for name, _ in attrs)

    Collector().feed(page)
    return tags, attributes


def test_dataset_and_config_text_is_escaped_in_every_report_format(hostile_run):
    from helpers import HOSTILE_IMAGE, HOSTILE_MODEL, HOSTILE_QUERY_FOLDER, HOSTILE_TAG

    from locretrieval.report.html import ALLOWED_TAGS

    markdown = (hostile_run.run / "report.md").read_text()
    html = (hostile_run.run / "report.html").read_text()
    for page in (markdown, html):
        assert "<img src=x" not in page and "<svg" not in page  # only their escaped text
    for name in (HOSTILE_QUERY_FOLDER, HOSTILE_TAG, HOSTILE_IMAGE, HOSTILE_MODEL):
        assert md_text(name) in markdown  # shown literally where it is named
    tags, attributes = report_markup(html)
    assert tags <= set(ALLOWED_TAGS) | {"html", "head", "meta", "title", "link", "style", "body", "nav"}
    assert [pair for pair in attributes if pair[1].startswith("on")] == []
    policy = re.search(r'<meta http-equiv="Content-Security-Policy" content="([^"]+)">', html).group(1)
    assert "default-src 'none'" in policy and "script-src" not in policy
    latex = "\n".join(path.read_text() for path in (hostile_run.run / "tables").glob("*.tex"))
    assert "\\input{x}" not in latex and "\\textbackslash input\\{x\\}" in latex
    scene = (hostile_run.run / "scene_3d.html").read_text()
    policy = re.search(r'<meta http-equiv="Content-Security-Policy" content="([^"]+)">', scene).group(1)
    scripts = re.findall(r"<script[^>]*>(.*?)</script>", scene, re.DOTALL)
    assert policy.count("'sha256-") == len(scripts) >= 2 and "unsafe-inline' " not in policy.split("style-src")[0]
    assert "<svg/onload" not in scene and "<img src=x" not in scene  # names only inside escaped JSON


def test_hydra_run_folders_keep_names_inside_outputs():
    from helpers import CONFIGS
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        config = compose("evaluate", overrides=["model.name='../../../x'"], return_hydra_config=True)
    run_dir = config.hydra.run.dir
    assert run_dir.startswith("outputs/evaluate/synthetic_mall/") and ".." not in run_dir.split("/")
    config.hydra.job.num = 0  # set by Hydra's launcher
    assert config.hydra.sweep.subdir.startswith("0_synthetic_mall_") and "/" not in config.hydra.sweep.subdir


@pytest.mark.parametrize(
    "name, problem",
    [
        ("/etc/hostname", "is absolute"),
        ("../../../secret/private.png", "has a '..' component"),
        ("cam/../../outside.png", "has a '..' component"),
        ("cam\\\\a.png", "has a backslash or a control character"),
    ],
)
def test_image_names_stay_inside_their_kapture_folder(tmp_path, name, problem):
    from locretrieval.scene.kapture_io import load_image_set

    root = phone_folder(tmp_path, {(1, "phone"): "a.png", (2, "phone"): "b.png"})
    records = root / "sensors" / "records_camera.txt"
    records.write_text(records.read_text().replace("b.png", name))
    with pytest.raises(KaptureFormatError, match=rf"records_camera\.txt:\d+: file name .* {re.escape(problem)}"):
        load_image_set(root)


@pytest.mark.parametrize(
    "parameters, problem",
    [
        ([64, 48, 50.0, 50.0, float("nan"), 24.0], r"parameters \[50\.0, 50\.0, nan, 24\.0\] must all be finite"),
        ([64, 48, 50.0, 50.0, 32.0, float("inf")], r"parameters \[50\.0, 50\.0, 32\.0, inf\] must all be finite"),
        ([64, 48, 50.0, 50.0, 640.0, 24.0], r"principal point \(640\.0, 24\.0\) lies outside the 64 x 48 image"),
        ([64, 48, 50.0, 50.0, 32.0, -3.0], r"principal point \(32\.0, -3\.0\) lies outside the 64 x 48 image"),
    ],
)
def test_camera_parameters_are_finite_and_the_principal_point_inside_the_image(tmp_path, parameters, problem):
    import kapture
    from kapture_folders import write_kapture

    from locretrieval.scene.kapture_io import load_image_set

    camera = kapture.Camera(kapture.CameraType.PINHOLE, parameters)
    root = write_kapture(tmp_path / "query", {"phone": camera}, {(1, "phone"): "a.png"})
    with pytest.raises(KaptureFormatError, match=rf"sensors\.txt:\d+: camera 'phone': {problem}"):
        load_image_set(root)


def test_a_query_folder_that_is_the_mapping_folder_is_refused_naming_both(tmp_path):
    from kapture_folders import PINHOLE, pose, write_kapture

    from locretrieval.scene.kapture_io import load_kapture_scene

    start, _ = pose("z", 1.0, [0.0, 0.0, 0.0])
    mapping = write_kapture(tmp_path / "mapping", {"phone": PINHOLE}, {(1, "phone"): "db/a.png"}, {(1, "phone"): start})
    linked = tmp_path / "query_link"
    linked.symlink_to(mapping)
    image = "sensors/records_data/db/a.png"
    for queries in (mapping, linked):
        message = rf"query image {queries}/{image} is the database image {mapping}/{image}"
        with pytest.raises(ValueError, match=message):
            load_kapture_scene("same", [mapping], [queries])


def test_kapture_text_that_is_not_utf8_names_file_and_line(tmp_path):
    from locretrieval.scene.kapture_io import load_image_set

    root = phone_folder(tmp_path, {(1, "phone"): "a.png"})
    sensors = root / "sensors" / "sensors.txt"
    sensors.write_bytes(sensors.read_bytes() + b"# caf\xe9\n")
    lines = sensors.read_bytes().count(b"\n")
    with pytest.raises(KaptureFormatError, match=rf"sensors\.txt:{lines}: not UTF-8 text \(invalid continuation byte"):
        load_image_set(root)


def test_a_decompression_bomb_names_the_image(tmp_path):
    from PIL import Image

    from locretrieval.errors import DataFileError
    from locretrieval.scene.images import read_image
    from locretrieval.scene.kapture_io import load_image_set

    root = phone_folder(tmp_path, {(1, "phone"): "a.png"})
    image = root / "sensors" / "records_data" / "a.png"
    Image.new("1", (20000, 20000)).save(image)  # 400 megapixels in 50 kB
    with pytest.raises(
        DataFileError, match=rf"{image}: not a readable image \(Image size \(400000000 pixels\) exceeds limit"
    ):
        load_image_set(root)
    with pytest.raises(DataFileError, match=rf"{image}: cannot decode this image file \(Image size"):
        read_image(image)


@pytest.mark.parametrize("damage", ["truncated", "empty"])
def test_a_damaged_cache_file_is_named_with_what_to_do(tmp_path, damage):
    from locretrieval.cache import load_arrays, save_arrays
    from locretrieval.errors import DataFileError

    path = tmp_path / "descriptors" / "key.npz"
    save_arrays(path, {"descriptors": np.ones((100, 8), dtype=np.float32)})
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2] if damage == "truncated" else b"")
    with pytest.raises(DataFileError, match=rf"{path}: not a readable \.npz file .*; delete it: it is recomputed"):
        load_arrays(path)


def test_atomic_writes_reach_the_disk_before_the_rename(tmp_path, monkeypatch):
    import os

    from locretrieval.cache import save_arrays

    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(
        os, "fsync", lambda fd: events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}"))) or real_fsync(fd)
    )
    monkeypatch.setattr(os, "replace", lambda a, b: events.append(("replace", str(a))) or real_replace(a, b))
    path = tmp_path / "cache" / "x.npz"
    save_arrays(path, {"a": np.arange(3)})
    temporary = next(name for kind, name in events if kind == "replace")
    assert events == [("fsync", temporary), ("replace", temporary), ("fsync", str(path.parent))]
