"""The 3D view (``scene_3d.html``): cameras at -R^T t, one selectable trace per ranking x paradigm
x method x k with its estimates, a file that carries plotly.js, and `make evaluate` writing it."""

import base64
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers import evaluate, evaluate_config
from hydra.utils import instantiate
from scipy.spatial.transform import Rotation

from locretrieval.config import validated
from locretrieval.estimates import ESTIMATED_POSE_COLUMNS, PoseEstimates, estimated_pose_table
from locretrieval.report.scene_view import SceneViewSettings, scene_figure, write_scene_view
from locretrieval.scene import Camera, ImageSet, Scene

FX, FY, CX, CY, WIDTH, HEIGHT = 50.0, 40.0, 32.0, 24.0, 64, 48


def view_settings(**changes) -> SceneViewSettings:
    """``report.scene_view`` as ``evaluate.yaml`` sets it, ``changes`` applied."""
    node = evaluate_config("paths.root_dir=/nonexistent").report.scene_view
    return validated(SceneViewSettings, {**node, **changes}, "report.scene_view")


def world_to_camera(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Random poses (wxyz, t) and, independently of locretrieval, their rotations and centres -R^T t."""
    rotations = Rotation.random(n, random_state=rng)
    t = rng.uniform(-10, 10, (n, 3))
    xyzw = rotations.as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1), t


def centres(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """c = -R^T t, with scipy's rotation of the wxyz quaternion."""
    R = Rotation.from_quat(np.concatenate([q[:, 1:], q[:, :1]], axis=1)).as_matrix()
    return -np.einsum("nji,nj->ni", R, t)


def image_set(prefix: str, q: np.ndarray, t: np.ndarray) -> ImageSet:
    camera = Camera("PINHOLE", WIDTH, HEIGHT, (FX, FY, CX, CY))
    return ImageSet([f"{prefix}{i}.png" for i in range(len(q))], "/x", [camera] * len(q), q, t)


def toy() -> tuple[Scene, list[PoseEstimates]]:
    """12 database cameras, 5 queries, two rankings' estimates with failures."""
    rng = np.random.default_rng(7)
    scene = Scene("toy", image_set("db", *world_to_camera(rng, 12)), image_set("q", *world_to_camera(rng, 5)))
    estimates = []
    for ranking, kind, paradigm, method, ks in (("netvlad", "descriptor", "approximation", "ewb", [1, 3]),
                                                ("gt_frustum", "groundtruth", "global_sfm", "pnp", [5])):  # fmt: skip
        q, t = world_to_camera(rng, len(ks) * 5)
        q, t = q.reshape(len(ks), 5, 4), t.reshape(len(ks), 5, 3)
        failures = np.full((len(ks), 5), "", dtype=object)
        missing = rng.random((len(ks), 5)) < 0.4
        q[missing], t[missing], failures[missing] = np.nan, np.nan, "too few inliers"
        estimates.append(PoseEstimates(ranking, kind, paradigm, method, ks, q, t, failures.astype(str)))
    return scene, estimates


def test_estimated_pose_table_has_a_row_per_estimate():
    scene, estimates = toy()
    table = estimated_pose_table("toy", estimates, scene.queries.names)
    assert list(table.columns) == ESTIMATED_POSE_COLUMNS
    assert len(table) == sum(int(np.isfinite(x.qvec[..., 0]).sum()) for x in estimates)
    by_key = {(e.ranking, e.paradigm, e.method): e for e in estimates}
    for row in table.itertuples():
        e = by_key[(row.ranking, row.paradigm, row.method)]
        n, query = e.ks.index(row.k), scene.queries.names.index(row.query)
        assert [row.qw, row.qx, row.qy, row.qz, row.tx, row.ty, row.tz] == pytest.approx(
            [*e.qvec[n, query], *e.tvec[n, query]]
        )
        assert (row.dataset, row.ranking_kind) == ("toy", e.ranking_kind)


def test_database_frusta_start_at_the_camera_centres_and_open_along_the_optical_axis():
    scene, estimates = toy()
    depth = 1.5
    figure = scene_figure(scene, estimated_pose_table("toy", estimates, scene.queries.names), None,
                          view_settings(frustum_depth_m=depth))  # fmt: skip
    database = figure.data[0]
    vertices = np.stack([database.x, database.y, database.z], axis=1).astype(float).reshape(len(scene.database), 11, 3)
    expected = centres(scene.database.qvec, scene.database.tvec)
    np.testing.assert_allclose(vertices[:, 5], expected, atol=1e-5)  # the stroke passes the centre at its 6th vertex
    np.testing.assert_allclose(vertices[:, 8], expected, atol=1e-5)
    assert np.isnan(vertices[:, 10]).all()  # a gap between cameras
    R = Rotation.from_quat(np.concatenate([scene.database.qvec[:, 1:], scene.database.qvec[:, :1]], axis=1)).as_matrix()
    corner = np.einsum("nij,nj->ni", R, vertices[:, 0]) + scene.database.tvec  # first corner, camera frame
    np.testing.assert_allclose(corner[:, 2], depth, atol=1e-5)  # at the frustum depth along +z
    np.testing.assert_allclose(FX * corner[:, 0] / corner[:, 2] + CX, 0.0, atol=1e-3)  # image corner (0, 0), pixels
    np.testing.assert_allclose(FY * corner[:, 1] / corner[:, 2] + CY, 0.0, atol=1e-3)


def selection_traces(data: list[dict]) -> dict[tuple, dict]:
    """The markers trace of each selection (those with ``meta`` and markers), by (ranking, paradigm, method, k)."""
    return {(t["meta"]["ranking"], t["meta"]["paradigm"], t["meta"]["method"], t["meta"]["k"]): t
            for t in data if t.get("meta") and t["mode"] == "markers"}  # fmt: skip


def test_each_ranking_paradigm_and_k_is_selectable_with_its_estimates():
    scene, estimates = toy()
    figure = scene_figure(scene, estimated_pose_table("toy", estimates, scene.queries.names), None, view_settings())
    data = [trace.to_plotly_json() for trace in figure.data]
    traces = selection_traces(data)
    expected = {(e.ranking, e.paradigm, e.method, k): (e, n) for e in estimates for n, k in enumerate(e.ks)}
    assert set(traces) == set(expected)
    for key, (e, n) in expected.items():
        found = np.isfinite(e.qvec[n, :, 0])
        trace = traces[key]
        points = np.stack([trace["x"], trace["y"], trace["z"]], axis=1)
        assert len(points) == found.sum(), key
        np.testing.assert_allclose(points, centres(e.qvec[n, found], e.tvec[n, found]), atol=1e-5)
    buttons = figure.layout.updatemenus[0].buttons
    assert len(buttons) == len(expected) + 1  # and "no estimate"
    first = data.index(traces[("netvlad", "approximation", "ewb", 1)])  # a descriptor ranking first
    assert buttons[0].label.startswith("netvlad") and buttons[0].args[0]["visible"][first]
    assert [t.get("visible", True) for t in data].count(True) == first + 2  # fixed traces, then one selection's two
    for button in buttons[:-1]:
        shown = [data[i] for i, visible in enumerate(button.args[0]["visible"]) if visible and data[i].get("meta")]
        assert len(shown) == 2 and shown[0]["meta"] == shown[1]["meta"] and button.label in shown[0]["name"]


def test_drawn_cameras_queries_and_map_points_are_bounded():
    scene, estimates = toy()
    poses = estimated_pose_table("toy", estimates, scene.queries.names)
    points = np.concatenate([np.random.default_rng(0).normal(size=(1000, 3)), [[1e6, 0.0, 0.0]]])  # one stray point
    settings = view_settings(max_cameras=4, max_queries=2, max_map_points=100, frustum_depth_m=1.0)
    data = [trace.to_plotly_json() for trace in scene_figure(scene, poses, points, settings).data]
    assert (
        len(data[0]["x"]) == 4 * 11
        and data[1]["name"] == "map points (100 of 1001, 1 far away left out)"
        and len(data[1]["x"]) == 100
    )
    kept = {"q0.png", "q4.png"}  # queries 0 and 4, evenly spaced
    for key, trace in selection_traces(data).items():
        expected = poses[
            (poses[["ranking", "paradigm", "method", "k"]].apply(tuple, axis=1) == key) & poses["query"].isin(kept)
        ]
        assert len(trace["x"]) == len(expected), key
    with pytest.raises(ValueError, match="'elsewhere.png'"):
        scene_figure(scene, poses.assign(query="elsewhere.png"), None, settings)
    with pytest.raises(ValueError, match=r"lack columns \['qw'\]"):
        scene_figure(scene, poses.drop(columns="qw"), None, settings)


def decoded(value):
    """A trace array as written to HTML (a list, or plotly's base64 typed array), as float64."""
    if isinstance(value, dict) and "bdata" in value:
        return np.frombuffer(base64.b64decode(value["bdata"]), dtype=np.dtype(value["dtype"])).astype(float)
    return np.asarray(value, dtype=float)


def html_traces(path: Path) -> list[dict]:
    """The traces of ``Plotly.newPlot(id, traces, layout, config)`` in a written HTML file."""
    text = path.read_text()
    start = text.index("[", text.index("Plotly.newPlot("))
    return json.JSONDecoder().raw_decode(text, start)[0]


def test_written_file_carries_plotly_js_and_the_same_traces(tmp_path):
    scene, estimates = toy()
    poses = estimated_pose_table("toy", estimates, scene.queries.names)
    path = write_scene_view(tmp_path / "scene_3d.html", scene, poses, None, view_settings(frustum_depth_m=2.0))
    text = path.read_text()
    assert "<script src=" not in text and "plotly.js v" in text  # plotly.js inline: opens from file://
    traces = html_traces(path)
    vertices = np.stack([decoded(traces[0][axis]) for axis in "xyz"], axis=1).reshape(len(scene.database), 11, 3)
    np.testing.assert_allclose(vertices[:, 5], centres(scene.database.qvec, scene.database.tvec), atol=1e-5)
    counts = {key: len(decoded(trace["x"])) for key, trace in selection_traces(traces).items()}
    assert counts == poses.groupby(["ranking", "paradigm", "method", "k"]).size().to_dict()


@pytest.mark.slow
def test_evaluate_writes_the_3d_view_with_the_map_and_links_it(tmp_path):
    overrides = [
        f"paths.root_dir={tmp_path}", "device=cpu", "report.figure_formats=[]", "paradigms.local_sfm.enabled=false",
        "paradigms.approximation.k=[1,3]", "paradigms.global_sfm.k=[2]", "groundtruth=default",
        "data.render.width=160", "data.render.height=120", "data.render.num_database=32", "data.render.num_queries=8",
        "data.render.texture_size=64", "data.render.length=20.0", "data.render.workers=1", "data.render.seed=3",
        "model.max_side=160", "model.step=4", "subsets.blur_width=160",
    ]  # fmt: skip
    cfg = evaluate_config(*overrides)
    run = tmp_path / "run"
    evaluate(cfg, run)
    assert "3D view: [scene_3d.html](scene_3d.html)" in (run / "report.md").read_text()
    poses = pd.read_csv(run / "estimated_poses.csv.gz", keep_default_na=False)
    errors = pd.read_csv(run / "query_errors.csv.gz", keep_default_na=False)
    assert len(poses) == (errors["failure"] == "").sum() > 0
    traces = html_traces(run / "scene_3d.html")
    scene = instantiate(cfg.data)
    vertices = np.stack([decoded(traces[0][axis]) for axis in "xyz"], axis=1).reshape(len(scene.database), 11, 3)
    np.testing.assert_allclose(vertices[:, 5], centres(scene.database.qvec, scene.database.tvec), atol=1e-5)
    assert traces[1]["name"].startswith("map points (") and len(decoded(traces[1]["x"])) > 0  # the global map was built
    counts = {key: len(decoded(trace["x"])) for key, trace in selection_traces(traces).items()}
    assert counts == poses.groupby(["ranking", "paradigm", "method", "k"]).size().to_dict()
    assert {p for _, p, _, _ in counts} == {"approximation", "global_sfm"}
    assert (run / "scene_3d.html").stat().st_size < 8 * 2**20
