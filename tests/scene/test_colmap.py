"""``data=colmap``: a COLMAP model written by pycolmap from a known scene (photos of a walk rendered
by the synthetic renderer, GPS in their EXIF) read back as a `Scene`: cameras, poses, the 3D points
its tracks share, the split, the metric scale and bad input."""

from __future__ import annotations

import json
import logging
import re
import shutil
from pathlib import Path

import helpers
import numpy as np
import pandas as pd
import pytest
from own_place import plain_photos, render_walk, write_model
from PIL import Image

from locretrieval import geometry
from locretrieval.build import scene_of
from locretrieval.config import ConfigError
from locretrieval.errors import DataFileError
from locretrieval.groundtruth import compute_groundtruths
from locretrieval.scene.colmap import SCENE_KEYS, SceneOptions
from locretrieval.scene.split import EveryNth

IMAGES = 15
CO_OBSERVATION = {"_target_": "locretrieval.groundtruth.CoObservationDefinition", "min_shared": 1, "query_pairs": 5}


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """15 photos of a walk, with GPS, and the tracks of 300 points on the shops across it."""
    root = tmp_path_factory.mktemp("colmap_walk")
    walk = render_walk(root / "photos", IMAGES, 96, 72, gps=True)
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(0.0, 20.0, 300), rng.uniform(3.0, 5.0, 300), rng.uniform(0.0, 4.0, 300)])
    tracks = [list(np.flatnonzero(visible(walk, point))) for point in points]
    return walk, points, [track for track in tracks if len(track) >= 2]


def visible(walk, point: np.ndarray) -> np.ndarray:
    """Which cameras of the walk see ``point`` (in front, inside the image)."""
    camera = np.einsum("nij,j->ni", geometry.quaternion_to_matrix(walk.qvec), point) + walk.tvec
    fx, fy, cx, cy = walk.camera.pinhole
    u, v = fx * camera[:, 0] / camera[:, 2] + cx, fy * camera[:, 1] / camera[:, 2] + cy
    return (camera[:, 2] > 0.1) & (u >= 0) & (u < walk.camera.width) & (v >= 0) & (v < walk.camera.height)


def model_of(walk_data, folder: Path, scale: float = 1.0, **options) -> Path:
    """The walk as a COLMAP model in ``folder``, its world ``scale`` times the metric one."""
    walk, points, tracks = walk_data
    tvec = scale * walk.tvec
    write_model(folder, walk.names, walk.camera, walk.qvec, tvec, tracks, scale * points, **options)
    return folder


def load(root: Path, model: Path, images: Path, *overrides: str):
    """``data=colmap`` composed as evaluate.py composes it, instantiated."""
    cfg = helpers.evaluate_config(
        "data=colmap", f"paths.root_dir={root}", f"data.model={model}", f"data.images={images}", *overrides
    )
    return scene_of(cfg.data)


@pytest.mark.parametrize("data", ["colmap", "photos"])
def test_the_scene_options_of_a_reconstruction_are_one_object_checked_before_any_file(tmp_path, data):
    """``data=colmap`` and ``data=photos`` share their keys besides the files (`SceneOptions`): the
    YAML's keys build it, and a key it does not take is named, with the nearest, before any file is read."""
    files = (f"paths.root_dir={tmp_path}", "data.images=nowhere", *(["data.model=sparse"] if data == "colmap" else []))
    keys = {key: helpers.evaluate_config(f"data={data}", *files, "data.unitless=true").data[key] for key in SCENE_KEYS}
    options = SceneOptions.from_keys("mine", keys)
    assert options.name == "mine" and options.scale.unitless and options.frustum_far == 50.0
    assert isinstance(options.split, EveryNth) and options.unsupported == {}
    with pytest.raises(ConfigError, match=r"^data.metres_per_unt: unknown key; .*did you mean metres_per_unit\?"):
        scene_of(helpers.evaluate_config(f"data={data}", *files, "+data.metres_per_unt=1"))
    with pytest.raises(ConfigError, match=r"^data.frustum_far: missing"):
        SceneOptions.from_keys("mine", {key: value for key, value in keys.items() if key != "frustum_far"})
    assert not list(tmp_path.rglob("*"))  # refused before any file is read or written


@pytest.mark.parametrize("text", [False, True], ids=["binary", "text"])
def test_a_model_written_by_pycolmap_round_trips_into_the_same_scene(tmp_path, walk, text):
    walk_scene, _, tracks = walk
    model = model_of(walk, tmp_path / "sparse", text=text)
    scene = load(tmp_path, model, walk_scene.folder, "data.metres_per_unit=1.0")
    queries = walk_scene.names[0::5]  # data/split=every_nth: every 5th in name order
    assert scene.queries.names == queries and scene.database.names == [n for n in walk_scene.names if n not in queries]
    assert all(tags == {"query"} for tags in scene.queries.tags)
    for images in (scene.database, scene.queries):
        rows = [walk_scene.names.index(name) for name in images.names]
        assert images.cameras == [walk_scene.camera] * len(rows)
        np.testing.assert_allclose(images.qvec, walk_scene.qvec[rows], atol=1e-9)
        np.testing.assert_allclose(images.tvec, walk_scene.tvec[rows], atol=1e-9)
    membership = np.zeros((IMAGES, len(tracks)), dtype=int)  # the tracks counted by hand
    for point, track in enumerate(tracks):
        membership[track, point] = 1
    query_rows = [walk_scene.names.index(n) for n in scene.queries.names]
    database_rows = [walk_scene.names.index(n) for n in scene.database.names]
    expected = membership[query_rows] @ membership[database_rows].T
    shared = scene.observations.shared(scene.queries.names, scene.database.names).toarray()
    np.testing.assert_array_equal(shared, expected)
    assert scene.quality.registered == scene.quality.images == IMAGES and scene.quality.points == len(tracks)
    assert scene.quality.mean_track_length == pytest.approx(membership.sum() / len(tracks))
    assert scene.quality.mean_reprojection_error_px < 1e-6  # the 2D points are the exact projections


def test_the_co_observation_ground_truth_counts_the_models_tracks_with_no_sfm_of_ours(tmp_path, walk):
    scene = load(tmp_path, model_of(walk, tmp_path / "sparse"), walk[0].folder, "data.metres_per_unit=1.0")
    settings = helpers.groundtruth_section({"co_observation": CO_OBSERVATION}, depth=50)
    cache = tmp_path / "cache"
    groundtruth = compute_groundtruths(scene, settings, helpers.sfm_settings(), cache)["co_observation"]
    shared = scene.observations.shared(scene.queries.names, scene.database.names).toarray()
    ranking = groundtruth.ranking
    for query in range(len(scene.queries)):
        ranked = ranking.indices[query][ranking.indices[query] >= 0]
        assert sorted(ranked.tolist()) == np.flatnonzero(shared[query]).tolist()  # every image sharing a point
        np.testing.assert_array_equal(ranking.scores[query][: len(ranked)], shared[query][ranked])
        assert (np.diff(shared[query][ranked]) <= 0).all()
    np.testing.assert_array_equal(groundtruth.relevance.toarray(), shared >= 1)
    assert sorted(path.name for path in cache.iterdir()) == ["groundtruth"]  # no features, matches or maps


def test_gps_in_the_photos_gives_metres_and_its_residual(tmp_path, walk):
    walk_scene = walk[0]
    scene = load(tmp_path, model_of(walk, tmp_path / "sparse", scale=0.37), walk_scene.folder)  # no scale key
    quality = scene.quality
    assert quality.scale_source == "gps" and quality.gps_images == IMAGES
    assert quality.metres_per_unit == pytest.approx(1 / 0.37, rel=1e-4)
    assert quality.gps_residual_rms_m < 0.01  # GPS written to 1e-6 arc seconds (3e-5 m)
    rows = [walk_scene.names.index(name) for name in scene.database.names]
    distances = geometry.pairwise_position_errors(scene.database.centers, scene.database.centers)
    truth = geometry.pairwise_position_errors(walk_scene.centres[rows], walk_scene.centres[rows])
    np.testing.assert_allclose(distances, truth, atol=0.01)  # metres, whatever the model's units
    assert "GPS of 15 images" in quality.summary()["scale"]


def without_exif(source: Path, target: Path) -> Path:
    """A copy of the photos of ``source`` without EXIF (no GPS)."""
    for path in source.rglob("*.jpg"):
        copy = target / path.relative_to(source)
        copy.parent.mkdir(parents=True, exist_ok=True)
        Image.open(path).save(copy, quality=95)
    return target


def test_without_gps_the_scale_is_given_or_the_run_stops_naming_the_three_ways(tmp_path, walk):
    walk_scene = walk[0]
    model = model_of(walk, tmp_path / "sparse", scale=0.5)
    photos = without_exif(walk_scene.folder, tmp_path / "photos")
    with pytest.raises(ConfigError) as raised:
        load(tmp_path, model, photos)
    message = str(raised.value)
    assert "found in 0 of the 15 registered images" in message
    assert "data.metres_per_unit" in message and "data.known_distance" in message and "GPS" in message
    first, last = walk_scene.names[1], walk_scene.names[-1]  # database images (every 5th from 0 are queries)
    truth = float(np.linalg.norm(walk_scene.centres[1] - walk_scene.centres[-1]))
    by_distance = load(tmp_path, model, photos, f"data.known_distance={{images: [{first}, {last}], metres: {truth}}}")
    by_factor = load(tmp_path, model, photos, "data.metres_per_unit=2.0")
    for scene in (by_distance, by_factor):  # the model at half the metric scale: 2 metres per unit
        rows = [walk_scene.names.index(name) for name in scene.database.names]
        np.testing.assert_allclose(scene.database.centers, walk_scene.centres[rows], atol=1e-6)
    assert by_distance.quality.scale_source == "known_distance"
    assert by_distance.quality.metres_per_unit == pytest.approx(2.0)
    unitless = load(tmp_path, model, photos, "data.unitless=true")
    assert "not metres" in unitless.quality.summary()["scale"]
    with pytest.raises(ConfigError, match="data.metres_per_unit and data.unitless both set the scale"):
        load(tmp_path, model, photos, "data.metres_per_unit=2.0", "data.unitless=true")
    with pytest.raises(ConfigError, match="data.known_distance.images: 'walk/nowhere.jpg' is not a registered image"):
        load(tmp_path, model, photos, f"data.known_distance={{images: [{first}, walk/nowhere.jpg], metres: 1.0}}")


def gps_place(root: Path, offsets: np.ndarray, altitudes: list[float | None]) -> tuple[Path, Path]:
    """15 flat photos 8 x 6 along 14 m (their GPS: each centre moved by its row of ``offsets``,
    metres east-north-up, at its altitude where given) and the model of their true centres at half
    the metric scale: ``(model, photos)``."""
    from locretrieval.scene import Camera

    centres = np.column_stack([np.linspace(0.0, 14.0, 15), 3.0 * np.sin(np.arange(15)), 0.1 * np.arange(15) % 0.7])
    names = plain_photos(root / "photos", centres + offsets, 8, 6, altitudes)
    camera = Camera("PINHOLE", 8, 6, (6.0, 6.0, 4.0, 3.0))
    qvec = np.tile([1.0, 0.0, 0.0, 0.0], (15, 1))
    write_model(root / "sparse", names, camera, qvec, -0.5 * centres, [], np.zeros((0, 3)))
    return root / "sparse", root / "photos"


def test_gps_altitudes_outside_the_earths_are_outliers(tmp_path, caplog):
    no_offset = np.zeros((15, 3))
    model, photos = gps_place(tmp_path / "one", no_offset, [4294967295.0] + [None] * 14)  # 2^32 - 1: wrapped
    with caplog.at_level(logging.WARNING):
        scene = load(tmp_path, model, photos)
    assert "1 GPS positions have altitudes outside Earth's (-11000.0, 9000.0) m (e.g. walk/000.jpg: 4.29497e+09 m)" in (
        caplog.text
    )
    assert scene.quality.gps_images == 14 and scene.quality.metres_per_unit == pytest.approx(2.0, rel=1e-5)
    model, photos = gps_place(tmp_path / "all", no_offset, [4294967295.0] * 15)
    with pytest.raises(
        ConfigError,
        match=r"found in 0 of the 15 registered images; 15 more hold altitudes outside Earth's \(-11000.0, 9000.0\) m",
    ):
        load(tmp_path, model, photos)


def test_gps_most_images_disagree_with_is_refused_saying_how_far_off(tmp_path):
    """Three groups of 5 photos, each group's GPS moved as one (none, 30 m east, 30 m north): the
    alignment fits one group exactly, the 10 others lie 30 m (or 42.4 m) off: refused."""
    offsets = np.array([[0.0, 0.0, 0.0], [30.0, 0.0, 0.0], [0.0, 30.0, 0.0]])[np.arange(15) % 3]
    model, photos = gps_place(tmp_path, offsets, [None] * 15)
    with pytest.raises(
        DataFileError,
        match=rf"^{photos}: the GPS positions of 10 of its 15 images with GPS lie farther than data.gps_max_error=10.0 "
        r"m from the camera centres of .*sparse aligned to them \(residuals: median 30(\.0\d*)? m, largest (30|42\.4)",
    ):
        load(tmp_path, model, photos)
    assert load(tmp_path, model, photos, "data.gps_max_error=50").quality.gps_images == 15


@pytest.mark.parametrize(
    ("split", "queries"),
    [
        (
            ["data/split=name_pattern", "data.split.pattern='[05][.]jpg$'"],
            ["walk/000.jpg", "walk/005.jpg", "walk/010.jpg"],
        ),
        (["data.split.step=4", "data.split.offset=1"], ["other/b.jpg", "walk/003.jpg", "walk/007.jpg", "walk/011.jpg"]),
        (["data/split=sequences", "data.split.sequences=[other]"], ["other/a.jpg", "other/b.jpg"]),
        (["data/split=list_file"], ["other/a.jpg", "walk/002.jpg"]),
    ],
    ids=["name_pattern", "every_nth", "sequences", "list_file"],
)
def test_a_split_part_chooses_the_queries(tmp_path, walk, split, queries):
    walk_scene, points, tracks = walk
    photos = tmp_path / "photos"
    shutil.copytree(walk_scene.folder, photos)
    (photos / "other").mkdir()
    for index, name in enumerate(["other/a.jpg", "other/b.jpg"]):  # a second sequence, at the first two poses
        Image.open(photos / walk_scene.names[index]).rotate(180).save(photos / name)
    names = [*walk_scene.names, "other/a.jpg", "other/b.jpg"]
    qvec, tvec = (
        np.concatenate([walk_scene.qvec, walk_scene.qvec[:2]]),
        np.concatenate([walk_scene.tvec, walk_scene.tvec[:2]]),
    )
    write_model(tmp_path / "sparse", names, walk_scene.camera, qvec, tvec, tracks, points)
    (tmp_path / "queries.txt").write_text("# queries\nwalk/002.jpg\n\nother/a.jpg\n")
    if "data/split=list_file" in split:
        split = [*split, f"data.split.path={tmp_path / 'queries.txt'}"]
    scene = load(tmp_path, tmp_path / "sparse", photos, "data.metres_per_unit=1", *split)
    assert scene.queries.names == queries
    assert sorted(scene.database.names) == sorted(set(names) - set(queries))


def test_a_list_file_within_its_byte_budget_naming_no_image_of_the_folder_names_its_line(tmp_path, walk, monkeypatch):
    (tmp_path / "queries.txt").write_text("walk/001.jpg\nwalk/missing.jpg\n")  # 30 bytes
    model = model_of(walk, tmp_path / "sparse")
    overrides = ("data.metres_per_unit=1", "data/split=list_file", f"data.split.path={tmp_path / 'queries.txt'}")
    with pytest.raises(DataFileError, match=r"queries.txt:2: 'walk/missing.jpg' is not an image of the image folder"):
        load(tmp_path, model, walk[0].folder, *overrides)
    helpers.set_limits(monkeypatch, list_file_bytes=29)
    with pytest.raises(DataFileError, match=r"queries.txt: 30 bytes, more than 29 \(limits.list_file_bytes; refused"):
        load(tmp_path, model, walk[0].folder, *overrides)


def test_unregistered_images_are_reported_and_left_out(tmp_path, walk, caplog):
    walk_scene = walk[0]
    photos = tmp_path / "photos"
    shutil.copytree(walk_scene.folder, photos)
    Image.open(photos / walk_scene.names[0]).rotate(90).save(photos / "walk" / "extra.jpg")  # in no model
    Image.open(photos / walk_scene.names[1]).rotate(90).save(photos / "walk" / "lost.jpg")  # not registered
    model = model_of(walk, tmp_path / "sparse", unregistered=("walk/lost.jpg",))
    with caplog.at_level(logging.WARNING):
        scene = load(tmp_path, model, photos, "data.metres_per_unit=1")
    assert "2 of 17 images are not registered" in caplog.text and "walk/extra.jpg" in caplog.text
    assert len(scene.database) + len(scene.queries) == IMAGES
    assert (scene.quality.registered, scene.quality.images) == (IMAGES, IMAGES + 2)
    assert scene.quality.summary()["registered images"] == "15 of 17 (88.2 %)"


def test_bad_input_names_the_problem(tmp_path, walk):
    walk_scene = walk[0]
    model = model_of(walk, tmp_path / "sparse")
    partial = tmp_path / "partial"
    shutil.copytree(walk_scene.folder, partial)
    for name in walk_scene.names[:3]:
        (partial / name).unlink()
    with pytest.raises(DataFileError, match=r"3 of its 15 registered images are missing from the image folder"):
        load(tmp_path, model, partial, "data.metres_per_unit=1")
    copied = tmp_path / "copied"
    shutil.copytree(walk_scene.folder, copied)
    shutil.copy(copied / walk_scene.names[4], copied / walk_scene.names[7])
    with pytest.raises(DataFileError, match=r"walk/007.jpg: the same image as .*walk/004.jpg"):
        load(tmp_path, model, copied, "data.metres_per_unit=1")
    resized = tmp_path / "resized"
    shutil.copytree(walk_scene.folder, resized)
    Image.open(resized / walk_scene.names[2]).resize((48, 36)).save(resized / walk_scene.names[2])
    with pytest.raises(
        DataFileError, match=r"walk/002.jpg: image is 48x36 pixels but its camera 1 in .*sparse is 96x72"
    ):
        load(tmp_path, model, resized, "data.metres_per_unit=1")
    with pytest.raises(FileNotFoundError, match=r"sparse_missing/cameras.bin \(or .txt\) not found"):
        (tmp_path / "sparse_missing").mkdir()
        load(tmp_path, tmp_path / "sparse_missing", walk_scene.folder, "data.metres_per_unit=1")


def test_a_run_without_a_metric_scale_names_model_units_everywhere(tmp_path, walk):
    from helpers import evaluate

    model = model_of(walk, tmp_path / "sparse", scale=0.5)
    photos = without_exif(walk[0].folder, tmp_path / "photos")
    cfg = helpers.evaluate_config(
        "data=colmap", f"paths.root_dir={tmp_path}", f"data.model={model}", f"data.images={photos}",
        "data.unitless=true", "device=cpu", "model.max_side=96", "model.step=4", "baselines.random=true",
        "paradigms.approximation.k=[1,3]", "paradigms.local_sfm.enabled=false", "paradigms.global_sfm.enabled=false",
        "groundtruth.enabled=[relative_pose]", "subsets.dynamic_masks=[]", "subsets.blur_width=160",
        "report.figure_formats=[]", "report.scene_view.enabled=false", "output.ltvl=false",
    )  # fmt: skip
    run = tmp_path / "run"
    evaluate(cfg, run)
    results = pd.read_csv(run / "results.csv")
    assert set(results["position_unit"]) == {"model units"}
    assert set(pd.read_csv(run / "median_errors.csv")["position_unit"]) == {"model units"}
    report = (run / "report.md").read_text()
    assert "5 model units, 10°" in report and "median position error (model units)" in report
    assert not re.search(r"\d m, \d", report)  # no threshold labelled in metres
    quality = json.loads((run / "summary.json").read_text())["pseudo ground truth"]
    assert quality["metres per model unit"] is None and "not metres" in quality["scale"]
