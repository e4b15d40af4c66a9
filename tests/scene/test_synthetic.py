"""The built-in synthetic scene: determinism, kapture output, geometry, SIFT geometry, conditions."""

import filecmp
import json
from pathlib import Path

import kapture
import kapture.io.csv as kapture_csv
import kapture.io.records as kapture_records
import numpy as np
import pycolmap  # noqa: E402  (after locretrieval)
import pytest
from helpers import evaluate_config, render_settings
from PIL import Image

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.build import scene_of
from locretrieval.config import ConfigError
from locretrieval.device import resolve_device
from locretrieval.scene.synthetic import render_synthetic_dataset
from locretrieval.scene.synthetic.camera import PinholeCamera
from locretrieval.scene.synthetic.config import EnvironmentBuilder
from locretrieval.scene.synthetic.dataset import ImagePlan, build_environment, render_plan, single_torch_thread
from locretrieval.scene.synthetic.dynamic import place_dynamic_objects
from locretrieval.scene.synthetic.mall import Mall
from locretrieval.scene.synthetic.render import Renderer
from locretrieval.scene.synthetic.trajectories import Viewpoint

HALF = {"night": 0.5, "blur": 0.5, "dynamic": 0.5, "noise": 0.5}
TINY = {
    "width": 96,
    "height": 72,
    "num_database": 8,
    "num_queries": 6,
    "texture_size": 64,
    "length": 20.0,
    "conditions": HALF,
    "database_dynamic": 0.5,
    "workers": 1,
    "seed": 5,
}
# 5 mapping stations 4 m apart (8 cameras each) in a 20 m corridor.
MEDIUM = {
    "width": 256,
    "height": 192,
    "num_database": 40,
    "num_queries": 12,
    "texture_size": 128,
    "length": 20.0,
    "conditions": HALF,
    "database_dynamic": 0.2,
    "workers": 1,
    "seed": 1,
}
CAMERAS_PER_STATION = 8


# --- helpers computed independently of the renderer ---------------------------------------------


def read_set(root: Path) -> dict:
    """Images of a kapture folder: name -> (camera params, R, t, depth, mask, tags)."""
    data = kapture_csv.kapture_from_dir(str(root))
    tags = {}
    lines = (root / "tags.txt").read_text().splitlines()
    assert lines[0] == "# image_name, tags"
    for line in lines[1:]:
        name, words = line.split(", ")
        tags[name] = set(words.split())
    depth_files = {ts: name for ts, sensor, name in kapture.flatten(data.records_depth)}
    images = {}
    for timestamp, sensor_id, name in kapture.flatten(data.records_camera):
        camera = data.sensors[sensor_id]
        width, height = int(camera.camera_params[0]), int(camera.camera_params[1])
        pose = data.trajectories[timestamp, sensor_id]
        depth_path = kapture_records.get_depth_map_fullpath(str(root), depth_files[timestamp])
        images[name] = {
            "camera": camera,
            "K": calibration(camera),
            "size": (width, height),
            "q": np.array(pose.r_raw),
            "R": geometry.quaternion_to_matrix(np.array(pose.r_raw)),
            "t": np.array(pose.t_raw),
            "depth": kapture_records.depth_map_from_file(depth_path, (width, height)),
            "mask": np.asarray(Image.open(root / "masks" / name)),
            "image": np.asarray(Image.open(kapture_records.get_image_fullpath(str(root), name))),
            "tags": tags[name],
        }
    return images


def calibration(camera) -> np.ndarray:
    params = [float(p) for p in camera.camera_params[2:]]
    fx, fy, cx, cy = params if camera.camera_type.name == "PINHOLE" else (params[0], params[0], params[1], params[2])
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def backproject(view: dict) -> tuple[np.ndarray, np.ndarray]:
    """World points of the pixel centres (COLMAP: (i + 0.5, j + 0.5)) with depth, and the valid mask."""
    width, height = view["size"]
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(view["K"]).T
    points_cam = rays * view["depth"][..., None]
    world = (points_cam - view["t"]) @ view["R"]  # R^T (x - t)
    return world, view["depth"] > 0


def high_frequency_energy(image: np.ndarray) -> float:
    gray = image.astype(np.float64).mean(axis=-1)
    laplacian = 4 * gray[1:-1, 1:-1] - gray[:-2, 1:-1] - gray[2:, 1:-1] - gray[1:-1, :-2] - gray[1:-1, 2:]
    return float(np.mean(laplacian**2))


# --- fixtures ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def medium(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synthetic_medium")
    render_synthetic_dataset(render_settings(MEDIUM), root)
    return root


@pytest.fixture(scope="module")
def medium_sets(medium) -> dict:
    return {"mapping": read_set(medium / "mapping"), "query": read_set(medium / "query")}


# --- configuration and determinism ---------------------------------------------------------------


def test_render_settings_are_the_yaml_checked_by_key():
    settings = render_settings({"environment": "street", "conditions": {"night": 1.0}})
    assert settings.environment == "street" and settings.conditions.night == 1.0
    yaml = evaluate_config("paths.root_dir=/nonexistent").data.render
    assert settings.conditions.blur == yaml.conditions.blur and settings.width == yaml.width
    assert type(settings.builder).__name__ == "Street"
    for changes, message in (
        ({"colour": 1}, r"data.render.colour: unknown key"),
        ({"conditions": {"rain": 0.1}}, r"data.render.conditions.rain: unknown key"),
        ({"environment": "forest"}, r"data.render.environment: must be a name of data.render.environments"),
        ({"width": 0}, r"data.render.width: must be a positive integer, got 0"),
        ({"blur_subframes": 4}, r"data.render.blur_subframes: must be odd"),
        ({"texture_size": 100}, r"data.render.texture_size: must be a power of two >= 16, got 100"),
        ({"length": 10.0}, r"data.render.length: must be between 20 and 500 metres"),
        ({"query_fov_deg": [55.0, 170.0]}, r"data.render.query_fov_deg: must be between 10 and 150 degrees"),
        ({"conditions": {"night": 1.5}}, r"data.render.conditions.night: must be a probability in \[0, 1\], got 1.5"),
        ({"noise_std": -0.1}, r"data.render.noise_std: must be >= 0"),
        ({"width": "wide"}, r"data.render.width: Value 'wide' of type 'str' could not be converted to Integer"),
    ):
        with pytest.raises(ConfigError, match=message):
            render_settings(changes)


def test_rendering_is_deterministic_and_seed_dependent(tmp_path):
    for folder, seed in (("a", 5), ("b", 5), ("c", 6)):
        render_synthetic_dataset(render_settings({**TINY, "seed": seed}), tmp_path / folder)
    for kapture_set in ("mapping", "query"):
        files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a" / kapture_set).rglob("*") if p.is_file())
        assert any(str(f).endswith(".depth") for f in files) and any("masks" in str(f) for f in files)
        match, mismatch, errors = filecmp.cmpfiles(tmp_path / "a", tmp_path / "b", files, shallow=False)
        assert not mismatch and not errors and len(match) == len(files)
        images = [f for f in files if str(f).endswith(".png") and "masks" not in str(f)]
        _, differing, _ = filecmp.cmpfiles(tmp_path / "a", tmp_path / "c", images, shallow=False)
        assert len(differing) == len(images)
    record = json.loads((tmp_path / "a" / "synthetic_config.json").read_text())
    assert record == render_settings({**TINY, "seed": 5}).record()
    assert record["environments"] == {"mall": {"_target_": "locretrieval.scene.synthetic.mall.Mall"}}


def test_forced_conditions_give_the_forced_tags(tmp_path):
    config = {**TINY, "conditions": {"night": 1.0, "blur": 0.0, "dynamic": 1.0, "noise": 0.0}, "database_dynamic": 1.0}
    render_synthetic_dataset(render_settings(config), tmp_path)
    queries = read_set(tmp_path / "query")
    database = read_set(tmp_path / "mapping")
    assert len(queries) == TINY["num_queries"] and len(database) == TINY["num_database"]
    assert all(view["tags"] == {"night", "dynamic"} for view in queries.values())
    assert all(view["tags"] == {"day", "dynamic"} for view in database.values())
    assert all((view["mask"] == 255).any() for view in [*queries.values(), *database.values()])


# --- kapture output -------------------------------------------------------------------------------


def test_kapture_output_reads_back(medium, medium_sets):
    mapping, query = medium_sets["mapping"], medium_sets["query"]
    assert len(mapping) == MEDIUM["num_database"] and len(query) == MEDIUM["num_queries"]
    assert sorted(mapping)[:2] == ["db/000000.png", "db/000001.png"]
    assert all(name.startswith("query/") for name in query)
    sensors_db = kapture_csv.sensors_from_file(str(medium / "mapping" / "sensors" / "sensors.txt"))
    sensors_q = kapture_csv.sensors_from_file(str(medium / "query" / "sensors" / "sensors.txt"))
    db_cameras = {view["camera"].name for view in mapping.values()}
    q_cameras = {view["camera"].name for view in query.values()}
    assert db_cameras == {"db_cam"} and len(q_cameras) >= 2 and not db_cameras & q_cameras
    for sensors, cameras in ((sensors_db, db_cameras), (sensors_q, q_cameras)):
        for camera_id in cameras:
            assert sensors[f"{camera_id}_depth"].sensor_type == "depth"
            assert sensors[f"{camera_id}_depth"].camera_params == sensors[camera_id].camera_params
    for views in (mapping, query):
        for name, view in views.items():
            width, height = view["size"]
            assert (width, height) == (MEDIUM["width"], MEDIUM["height"])
            assert view["image"].shape == (height, width, 3) and view["image"].dtype == np.uint8
            assert view["K"][0, 2] == width / 2 and view["K"][1, 2] == height / 2  # COLMAP: centred camera
            assert np.linalg.norm(view["q"]) == pytest.approx(1.0, abs=1e-9)
            assert view["depth"].shape == (height, width) and view["depth"].dtype == np.float32
            assert np.isfinite(view["depth"]).all() and (view["depth"] > 0.1).mean() > 0.95  # mall: no sky
            assert view["mask"].shape == (height, width) and set(np.unique(view["mask"])) <= {0, 255}
            assert ("dynamic" in view["tags"]) == bool(view["mask"].any()), name
            assert len(view["tags"] & {"day", "night"}) == 1
    assert all(view["tags"] <= {"day", "dynamic"} for view in mapping.values())
    assert {"night", "blur", "dynamic", "noise"} <= set().union(*(view["tags"] for view in query.values()))


# --- geometry ----------------------------------------------------------------------------------------


def test_depth_matches_the_analytic_floor_in_colmap_pixel_convention(medium_sets):
    """Floor pixels (world z = 0) have the depth of the ray through the pixel centre (i + 0.5, j + 0.5);
    a half-pixel error in the convention would be off by far more than the tolerance."""
    checked = 0
    for view in list(medium_sets["mapping"].values())[:8]:
        world, valid = backproject(view)
        floor = valid & (np.abs(world[..., 2]) < 1e-3)
        if floor.sum() < 100:  # e.g. a view of the end wall
            continue
        width, height = view["size"]
        u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        rays_world = (np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(view["K"]).T) @ view["R"]
        center = -view["R"].T @ view["t"]
        expected = -center[2] / rays_world[..., 2]  # ray parameter = depth (camera-frame z = 1)
        relative = np.abs(view["depth"][floor] - expected[floor]) / expected[floor]
        assert np.median(relative) < 1e-6 and np.percentile(relative, 99) < 1e-4  # float32 at grazing angles
        shifted = (
            -center[2]
            / ((np.stack([u - 0.5, v - 0.5, np.ones_like(u)], -1) @ np.linalg.inv(view["K"]).T) @ view["R"])[..., 2]
        )
        assert np.median(np.abs(view["depth"][floor] - shifted[floor]) / shifted[floor]) > 1e-3
        checked += floor.sum()
    assert checked > 5000, "too few pixels back-project onto the floor plane z = 0"


def test_depth_and_poses_agree_between_nearby_views(medium_sets):
    """Pixels of view A back-projected with their depth and projected into B (next station, same
    heading) land on B's depth where visible, and never in front of the surface B sees."""
    mapping = medium_sets["mapping"]
    names = sorted(mapping)
    for a in (0, 2, 1, 9):
        A, B = mapping[names[a]], mapping[names[a + CAMERAS_PER_STATION]]
        world, valid = backproject(A)
        points = world[valid]
        cam_b = points @ B["R"].T + B["t"]
        projected = cam_b @ B["K"].T
        u, v = projected[:, 0] / projected[:, 2], projected[:, 1] / projected[:, 2]
        width, height = B["size"]
        inside = (cam_b[:, 2] > 0.1) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
        seen = B["depth"][v[inside].astype(int), u[inside].astype(int)]
        z = cam_b[inside, 2]
        agree = np.abs(z - seen) < 0.03 + 0.005 * z
        in_front = z < seen - (0.05 + 0.02 * z)
        assert inside.sum() > 0.2 * valid.sum()
        assert agree.mean() > 0.6, (a, agree.mean())
        assert in_front.mean() < 0.03, (a, in_front.mean())


def sift(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pycolmap.logging.minloglevel = 2
    extractor = pycolmap.FeatureExtractor.create(pycolmap.FeatureExtractionOptions())
    keypoints, descriptors = extractor.extract_from_uint8_array(np.asarray(Image.fromarray(image).convert("L")))
    xy = np.array([[k.x, k.y] for k in keypoints]).reshape(-1, 2)
    return xy, np.asarray(descriptors.data, dtype=np.float32)


def mutual_ratio_matches(d1: np.ndarray, d2: np.ndarray, ratio: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    d1 = d1 / np.linalg.norm(d1, axis=1, keepdims=True)
    d2 = d2 / np.linalg.norm(d2, axis=1, keepdims=True)
    distance = np.sqrt(np.maximum(2.0 - 2.0 * d1 @ d2.T, 0.0))
    nearest12, nearest21 = distance.argmin(1), distance.argmin(0)
    two = np.sort(distance, axis=1)[:, :2]
    keep = (nearest21[nearest12] == np.arange(len(d1))) & (two[:, 0] < ratio * two[:, 1])
    return np.flatnonzero(keep), nearest12[keep]


def sampson_errors(x1: np.ndarray, x2: np.ndarray, F: np.ndarray) -> np.ndarray:
    h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
    Fx1, Ftx2 = h1 @ F.T, h2 @ F
    numerator = np.sum(h2 * Fx1, axis=1) ** 2
    return np.sqrt(numerator / (Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2))


def test_sift_matches_agree_with_the_known_relative_pose(medium_sets):
    """SIFT (pycolmap) + mutual NN + ratio test between nearby database views: most matches
    satisfy the epipolar geometry of the written poses and intrinsics."""
    mapping = medium_sets["mapping"]
    names = sorted(mapping)
    for a in (0, 9, 10):  # along +x, across towards +y, along -x; the next station 4 m further
        A, B = mapping[names[a]], mapping[names[a + CAMERAS_PER_STATION]]
        R = B["R"] @ A["R"].T
        t = B["t"] - R @ A["t"]
        skew = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        F = np.linalg.inv(B["K"]).T @ skew @ R @ np.linalg.inv(A["K"])
        (xy_a, d_a), (xy_b, d_b) = sift(A["image"]), sift(B["image"])
        i, j = mutual_ratio_matches(d_a, d_b)
        errors = sampson_errors(xy_a[i], xy_b[j], F)
        assert np.sum(errors < 2.0) > 50, (a, np.sum(errors < 2.0))
        assert np.mean(errors < 2.0) > 0.7, (a, np.mean(errors < 2.0))
        # The same matches against a wrong geometry (the two views swapped) are not consistent.
        assert np.mean(sampson_errors(xy_a[i], xy_b[j], F.T) < 2.0) < 0.5 * np.mean(errors < 2.0)


# --- conditions ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene():
    config = render_settings({**MEDIUM, "width": 160, "height": 120})
    with single_torch_thread():  # as render_synthetic_dataset does
        environment = build_environment(config)
        renderer = Renderer(environment, resolve_device("cpu"))
        camera = PinholeCamera.centred("q", "SIMPLE_PINHOLE", 160, 120, 60.0)
        viewpoint = Viewpoint(np.array([6.0, -1.0, 1.6]), 10.0, 0.0, 0.0)
        yield config, environment, renderer, camera, viewpoint


def rendered(scene, tags, objects=None):
    config, environment, renderer, camera, viewpoint = scene
    plan = ImagePlan("query", 0, camera, viewpoint, set(tags), objects)
    return render_plan(renderer, environment, plan, config)


def test_night_blur_and_noise_change_the_image(scene):
    day, day_depth, _ = rendered(scene, {"day"})
    night, night_depth, _ = rendered(scene, {"night"})
    assert night.mean() < 0.7 * day.mean()
    np.testing.assert_array_equal(night_depth, day_depth)
    # Night light is not a global gain: the night/day ratio varies strongly across the image.
    ratio = (night.astype(float).mean(-1) + 1) / (day.astype(float).mean(-1) + 1)
    assert np.percentile(ratio, 90) > 2.0 * np.percentile(ratio, 10)
    blurred, blurred_depth, _ = rendered(scene, {"day", "blur"})
    assert high_frequency_energy(blurred) < 0.6 * high_frequency_energy(day)
    np.testing.assert_array_equal(blurred_depth, day_depth)  # depth of the mid-exposure pose
    noisy, _, _ = rendered(scene, {"day", "noise"})
    difference = noisy.astype(float) - day.astype(float)
    assert abs(difference.mean()) < 2.0 and 3.0 < difference.std() < 20.0
    assert high_frequency_energy(noisy) > 1.5 * high_frequency_energy(day)


def test_masks_cover_the_dynamic_objects(scene):
    config, environment, renderer, camera, viewpoint = scene
    objects = place_dynamic_objects(
        environment, renderer, camera, viewpoint.rotation, viewpoint.center, 3, np.random.default_rng(0)
    )
    assert len(objects) >= 3  # at least one person (three boxes)
    clean, clean_depth, clean_mask = rendered(scene, {"day"})
    busy, busy_depth, busy_mask = rendered(scene, {"day", "dynamic"}, objects)
    assert not clean_mask.any() and 0.01 < busy_mask.mean() < 0.8
    changed = np.abs(busy.astype(int) - clean.astype(int)).max(-1) > 0
    assert not (changed & ~busy_mask).any()  # nothing outside the mask changes
    assert changed[busy_mask].mean() > 0.9
    assert (busy_depth[busy_mask] < clean_depth[busy_mask]).all()  # occluders are in front


def test_textures_are_area_filtered_like_a_supersampled_reference(scene):
    """One sample per pixel with mipmapping has about the high-frequency energy of a 3x3
    supersampled render; point-sampled textures would alias (2-3x more energy here)."""
    config, environment, renderer, camera, _ = scene
    for viewpoint in (
        Viewpoint(np.array([3.0, -1.0, 1.6]), 5.0, -3.0, 0.0),
        Viewpoint(np.array([3.0, 1.0, 1.6]), 30.0, -10.0, 0.0),
    ):
        single = renderer.render(camera, viewpoint.rotation, viewpoint.center, environment.day, supersampling=1)
        reference = renderer.render(camera, viewpoint.rotation, viewpoint.center, environment.day, supersampling=3)
        np.testing.assert_array_equal(single.depth, reference.depth)
        assert high_frequency_energy(single.rgb) < 1.5 * high_frequency_energy(reference.rgb)
        assert np.abs(single.rgb - reference.rgb).mean() < 0.025


def test_staging_folders_of_killed_renders_are_removed_and_live_ones_kept(tmp_path):
    import os

    from locretrieval.scene.synthetic.dataset import STAGING_PREFIX, remove_stale_staging

    dead = tmp_path / f"{STAGING_PREFIX}999999999-abc"  # no such process
    live = tmp_path / f"{STAGING_PREFIX}{os.getpid()}-def"
    for folder in (dead, live):
        (folder / "mapping").mkdir(parents=True)
    assert remove_stale_staging(tmp_path) == [dead]
    assert not dead.exists() and live.exists()


BUILT = []


class RecordedMall(EnvironmentBuilder):
    """An environment from outside the package: the mall, each build recorded."""

    def build(self, rng, length, texture_size):
        BUILT.append((length, texture_size))
        return Mall().build(rng, length, texture_size)


def test_an_environment_from_outside_the_package_is_chosen_through_the_config(tmp_path, monkeypatch):

    tiny = [f"data.render.{key}={value}" for key, value in TINY.items() if key != "conditions"]
    common = ["device=cpu", f"paths.root_dir={tmp_path}", f"paths.cache_dir={tmp_path / 'cache'}", *tiny]
    node = f"{{_target_: {__name__}.RecordedMall}}"
    cfg = evaluate_config(*common, f"+data.render.environments.recorded={node}", "data.render.environment=recorded")
    recorded = scene_of(cfg.data)
    assert recorded.name == "synthetic_recorded" and BUILT == [(TINY["length"], TINY["texture_size"])]
    mall = scene_of(evaluate_config(*common).data)
    assert mall.database.paths != recorded.database.paths  # rendered into a folder of its own
    for ours, theirs in zip(recorded.database.paths + recorded.queries.paths, mall.database.paths + mall.queries.paths):
        assert filecmp.cmp(ours, theirs, shallow=False)  # the mall's images, by the same seed
