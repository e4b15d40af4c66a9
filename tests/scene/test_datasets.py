"""Dataset configs composed with Hydra and instantiated against tiny kapture layouts; real datasets as
NAVER's downloader installs them: for each dataset, a miniature of its folder tree (kapture folders
with the dataset's image naming, published global-feature names under
``<dataset>/global_features/<name>/global_features``, R2D2-named local features under
``<dataset>/local_features/r2d2_WASF-N8_20k/{keypoints,descriptors}``) built from a tiny rendered
scene, and ``evaluate.py data=<name> model=precomputed model.feature_name=<name>`` end to end."""

from __future__ import annotations

import os
import re
import shutil
from dataclasses import replace
from pathlib import Path

import helpers
import numpy as np
import pandas as pd
import pytest
from helpers import evaluate, render_settings
from hydra import compose, initialize_config_dir
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from kapture_folders import PINHOLE, pose, write_kapture
from published_layouts import LAYOUTS, install, split

from locretrieval.build import scene_of
from locretrieval.config import ConfigError
from locretrieval.scene import Scene
from locretrieval.scene.datasets import DatasetNotFoundError
from locretrieval.scene.ltvl import KaptureNames, LtvlNames, WithoutFirstFolder, write_ltvl
from locretrieval.sfm.pairs import database_pairs, overlapping_pairs

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
#: What the end-to-end runs on the downloaders' layouts do not read, left out: the report's 3D view and
#: all but 100 bootstrap resamples (report.md and every table are still written; their intervals are not checked).
UNREAD = ["report.scene_view.enabled=false", "metrics.uncertainty.resamples=100"]
DATASETS = ["aachen", "baidu", "robotcar", "robotcar_v2", "gangnam", "inloc"]


def compose_data(dataset: str, *overrides: str):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose("evaluate", overrides=[f"data={dataset}", *overrides])


@pytest.fixture(autouse=True)
def no_data_env(monkeypatch):
    monkeypatch.delenv("LOCRETRIEVAL_DATA", raising=False)


def kapture_folder(root: Path, names: list[str], posed: bool) -> Path:
    """A one-camera kapture folder; images posed at distinct positions when ``posed``."""
    records = {(i, "phone"): name for i, name in enumerate(names)}
    trajectories = (
        {(i, "phone"): pose("z", 10.0 * i, [float(i), 0.0, 1.0])[0] for i in range(len(names))} if posed else None
    )
    return write_kapture(root, {"phone": PINHOLE}, records, trajectories)


def test_every_data_config_has_the_same_keys():
    configs = {dataset: compose_data(dataset, "paths.data_dir=/d").data for dataset in [*DATASETS, "kapture"]}
    assert len({frozenset(cfg) for cfg in configs.values()}) == 1
    assert {"_target_", "name", "root", "mapping", "queries", "ltvl_names", "frustum_far"} <= set(configs["aachen"])
    for dataset in DATASETS:
        cfg = configs[dataset]
        assert cfg.name == dataset
        assert cfg.ltvl_names._target_.startswith("locretrieval.scene.ltvl.")
        assert cfg.frustum_far in (25.0, 50.0)
        assert cfg.root == "/d"


@pytest.mark.parametrize(
    ("dataset", "min_radius", "max_per_image"),
    [
        ("aachen", 10.0, None),
        ("baidu", 10.0, None),
        ("robotcar", 0.0, 50),
        ("robotcar_v2", 0.0, 50),
        ("gangnam", 0.0, 50),
    ],
)
def test_data_configs_set_the_papers_settings(dataset, min_radius, max_per_image):
    cfg = compose_data(dataset)
    assert (cfg.sfm.map_pairs.min_radius, cfg.sfm.map_pairs.max_per_image) == (min_radius, max_per_image)
    assert cfg.sfm.features._target_.endswith("KaptureFeatures") and cfg.sfm.features.name == "r2d2_WASF-N8_20k"
    # the reference registrator: COLMAP's image_registrator on two-view verified matches
    assert (cfg.sfm.pnp.max_error, cfg.sfm.pnp.min_num_inliers, cfg.sfm.pnp.min_inlier_ratio) == (12.0, 30, 0.25)
    assert cfg.sfm.query_verification._target_.endswith("TwoViewVerification")
    assert cfg.sfm.triangulation == compose_data("synthetic").sfm.triangulation  # the rest: the defaults
    assert (
        compose_data(dataset, "sfm.map_pairs.max_per_image=7").sfm.map_pairs.max_per_image == 7
    )  # the command line wins
    own = compose_data(dataset, "sfm=default").sfm
    assert own.pnp.min_num_inliers == 12 and own.map_pairs.min_radius == min_radius  # the paper's pairs stay
    assert own.features._target_.endswith("SiftFeatures") and own.query_verification._target_.endswith("NoVerification")
    synthetic = compose_data("synthetic").sfm
    assert (
        synthetic.features._target_.endswith("SiftFeatures")
        and synthetic.pnp.min_num_inliers == 12
        and synthetic.map_pairs.max_per_image == 20
    )


@pytest.mark.parametrize("dataset", DATASETS)
def test_missing_dataset_names_expected_path_and_how_to_get_it(dataset, tmp_path):
    cfg = compose_data(dataset, f"paths.data_dir={tmp_path}/nowhere")
    with pytest.raises(InstantiationException) as raised:
        instantiate(cfg.data)
    error = raised.value.__cause__
    assert isinstance(error, DatasetNotFoundError)
    first = cfg.data.mapping if isinstance(cfg.data.mapping, str) else cfg.data.mapping[0]
    message = str(error)
    assert f"kapture folder not found: {tmp_path}/nowhere/{first}" in message
    assert "kapture_download_dataset.py update" in message and "kapture_download_dataset.py install" in message
    assert "LOCRETRIEVAL_DATA" in message and "paths.data_dir" in message


def test_aachen_layout_loads_with_day_night_tags_from_env_root(tmp_path, monkeypatch):
    base = tmp_path / "Aachen-Day-Night-v1.1"
    kapture_folder(base / "mapping", ["db/1.jpg", "db/2.jpg"], posed=True)
    kapture_folder(base / "query_day", ["query/day/milestone/a.jpg"], posed=False)
    kapture_folder(base / "query_night", ["query/night/nexus5x/b.jpg"], posed=False)
    monkeypatch.setenv("LOCRETRIEVAL_DATA", str(tmp_path))
    cfg = compose_data("aachen", "paths.root_dir=/not/used")
    scene = instantiate(cfg.data)
    assert isinstance(scene, Scene) and scene.name == "aachen"
    assert scene.database.names == ["db/1.jpg", "db/2.jpg"]
    assert scene.queries.names == ["query/day/milestone/a.jpg", "query/night/nexus5x/b.jpg"]
    assert scene.queries.tags == [frozenset({"day"}), frozenset({"night"})]
    assert not scene.queries.has_pose.any()
    assert [scene.ltvl_names(n) for n in scene.queries.names] == ["a.jpg", "b.jpg"]
    assert scene.sources == [base / "mapping", base / "query_day", base / "query_night"]


def test_robotcar_v2_locations_and_conditions(tmp_path):
    base = tmp_path / "RobotCar_Seasons-v2"
    kapture_folder(
        base / "01" / "mapping", ["overcast-reference/rear/1.jpg", "overcast-reference/rear/2.jpg"], posed=True
    )
    kapture_folder(base / "02" / "mapping", ["overcast-reference/rear/3.jpg", "snow/rear/4.jpg"], posed=True)
    kapture_folder(base / "01" / "query", ["night-rain/rear/5.jpg", "dawn/rear/6.jpg"], posed=False)
    kapture_folder(base / "02" / "query", ["night/rear/7.jpg"], posed=False)
    cfg = compose_data("robotcar_v2", f"paths.data_dir={tmp_path}")
    scene = instantiate(cfg.data)
    assert len(scene.database) == 4
    assert scene.queries.names == ["night-rain/rear/5.jpg", "dawn/rear/6.jpg", "night/rear/7.jpg"]
    assert scene.queries.tag_mask("night").tolist() == [True, False, True]
    assert scene.queries.tag_mask("day").tolist() == [False, True, False]
    assert all("query" in tags for tags in scene.queries.tags)
    assert scene.queries.paths[2] == base / "02/query/sensors/records_data/night/rear/7.jpg"
    assert [scene.ltvl_names(n) for n in scene.queries.names] == [
        "rear/5.jpg",
        "rear/6.jpg",
        "rear/7.jpg",
    ]


def test_robotcar_v1_is_the_default_with_posed_queries_and_v2s_images(tmp_path):
    v1 = tmp_path / "RobotCar_Seasons-v1"
    kapture_folder(v1 / "mapping", ["overcast-reference/rear/1.jpg", "snow/rear/2.jpg"], posed=True)
    kapture_folder(v1 / "query", ["night/rear/3.jpg", "dawn/rear/4.jpg"], posed=True)
    # The downloader's v1 has no images: records_data link to v2's merged images (NAVER's instructions).
    images = tmp_path / "RobotCar_Seasons-v2" / "all" / "sensors" / "records_data"
    for folder in (v1 / "mapping", v1 / "query"):
        records = folder / "sensors" / "records_data"
        shutil.copytree(records, images, dirs_exist_ok=True)
        shutil.rmtree(records)
        records.symlink_to(os.path.relpath(images, records.parent))
    cfg = compose_data("robotcar", f"paths.data_dir={tmp_path}")
    assert "mv mapping_wo_images mapping" in cfg.data.install
    scene = instantiate(cfg.data)
    assert scene.name == "robotcar" and len(scene.database) == 2
    assert np.isfinite(scene.queries.tvec).all()  # v1 queries have reference poses
    assert scene.queries.tag_mask("night").tolist() == [True, False]
    assert scene.queries.paths[0].resolve() == (images / "night/rear/3.jpg").resolve()


@pytest.mark.parametrize(
    ("dataset", "mapping", "queries", "tags"),
    [
        ("baidu", "baidu-mall/mapping", ["baidu-mall/query"], [{"query"}]),
        (
            "gangnam",
            "GangnamStation/B2/release/mapping",
            ["GangnamStation/B2/release/validation", "GangnamStation/B2/release/test"],
            [{"validation"}, {"test"}],
        ),
        ("inloc", "InLoc/mapping", ["InLoc/query"], [{"query"}]),
    ],
)
def test_dataset_layouts_load(tmp_path, dataset, mapping, queries, tags):
    kapture_folder(tmp_path / mapping, ["db/1.jpg"], posed=True)
    for i, folder in enumerate(queries):
        kapture_folder(tmp_path / folder, [f"q{i}/{i}.jpg"], posed=i == 0)
    scene = instantiate(compose_data(dataset, f"paths.data_dir={tmp_path}").data)
    assert scene.name == dataset
    assert scene.database.names == ["db/1.jpg"]
    assert scene.queries.names == [f"q{i}/{i}.jpg" for i in range(len(queries))]
    assert scene.queries.tags == [frozenset(t) for t in tags]
    assert scene.sources == [tmp_path / folder for folder in [mapping, *queries]]


def test_generic_kapture_config(tmp_path):
    mapping = kapture_folder(tmp_path / "map", ["a.jpg"], posed=True)
    query = kapture_folder(tmp_path / "late_queries", ["b.jpg"], posed=True)
    cfg = compose_data("kapture", "paths.data_dir=/unused", f"data.mapping={mapping}", f"data.queries=[{query}]")
    scene = instantiate(cfg.data)
    assert scene.name == "kapture"
    assert scene.queries.tags == [frozenset({"late_queries"})]
    assert scene.queries.has_pose.all()
    relative = compose_data(
        "kapture",
        f"paths.data_dir={tmp_path}",
        "data.mapping=map",
        "data.queries=[late_queries]",
        "data.query_tags=[late]",
    )
    assert instantiate(relative.data).queries.tags == [frozenset({"late"})]
    with pytest.raises(Exception, match="Missing mandatory value: data.mapping"):
        instantiate(compose_data("kapture", "paths.data_dir=/unused").data)


def test_bad_dataset_settings_fail_before_loading(tmp_path):
    with pytest.raises(
        ConfigError,
        match=r"data.ltvl_names: a LtvlNames is chosen by its config group now: data/ltvl_names=basename \(configs/",
    ):
        scene_of(compose_data("baidu", f"paths.data_dir={tmp_path}", "data.ltvl_names=basename").data)
    with pytest.raises(InstantiationException, match="frustum_far must be a positive distance"):
        instantiate(compose_data("baidu", f"paths.data_dir={tmp_path}", "data.frustum_far=0").data)
    with pytest.raises(InstantiationException, match=r"1 query_tags \['x'\] for 2 query entries"):
        instantiate(compose_data("gangnam", f"paths.data_dir={tmp_path}", "data.query_tags=[x]").data)


def test_synthetic_street_is_rendered_once_whatever_the_workers_and_auto_device(tmp_path, caplog):
    import logging

    import numpy as np

    from locretrieval.scene.datasets import load_synthetic_dataset

    render = {"environment": "street", "width": 64, "height": 48, "num_database": 8, "num_queries": 4,
              "texture_size": 32, "length": 20.0,
              "conditions": {"night": 0.0, "blur": 0.0, "dynamic": 1.0, "noise": 0.0},
              "workers": 1, "device": "cpu", "seed": 2}  # fmt: skip
    facts = {"ltvl_names": KaptureNames(), "frustum_far": 25.0}
    first = load_synthetic_dataset("street", tmp_path, render_settings(render), **facts)
    with caplog.at_level(logging.INFO):
        auto = render_settings({**render, "workers": 2, "device": "auto"})
        again = load_synthetic_dataset("street", tmp_path, auto, **facts)
    assert (again.ltvl_names, again.frustum_far) == (KaptureNames(), 25.0)  # dataset facts kept on the scene
    assert "synthetic scene cached" in caplog.text and again.database.paths == first.database.paths
    assert len([path for path in (tmp_path / "synthetic").iterdir() if path.is_dir()]) == 1  # and its render lock
    masks = [
        np.load(p) if p.suffix == ".npy" else np.asarray(__import__("PIL.Image").Image.open(p))
        for p in first.queries.mask_paths
    ]
    assert any(mask.any() for mask in masks)  # every query has people/vehicles (dynamic: 1.0)


def test_a_missing_dataset_is_reported_once_with_its_lines_as_written(tmp_path):
    """``python evaluate.py data=baidu`` without the dataset: its message (path expected, how to
    get it) appears once in what the user sees, on its own lines, and the run fails."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    command = [sys.executable, str(root / "evaluate.py"), "data=baidu", f"paths.root_dir={tmp_path}",
               f"paths.data_dir={tmp_path}/nowhere", f"hydra.run.dir={tmp_path}/run"]  # fmt: skip
    completed = subprocess.run(command, cwd=root, capture_output=True, text=True, timeout=300)
    shown = completed.stdout + completed.stderr
    assert completed.returncode != 0
    assert shown.count(f"kapture folder not found: {tmp_path}/nowhere/") == 1, shown[-3000:]
    assert "kapture_download_dataset.py install" in shown.split(f"kapture folder not found: {tmp_path}")[1]
    lines = [line.strip() for line in shown.splitlines()]
    assert "kapture_download_dataset.py update" in lines  # its lines as lines, not inside a one-line repr
    assert "InstantiationException" not in shown


class ShoutedNames(LtvlNames):
    """LTVL names from outside the package: the file name, upper case."""

    def __call__(self, name):
        return Path(name).name.upper()


def test_ltvl_names_from_outside_the_package_are_chosen_through_the_config(tmp_path, monkeypatch):
    base = tmp_path / "Aachen-Day-Night-v1.1"
    kapture_folder(base / "mapping", ["db/1.jpg", "db/2.jpg"], posed=True)
    kapture_folder(base / "query_day", ["query/day/milestone/a.jpg"], posed=False)
    kapture_folder(base / "query_night", ["query/night/nexus5x/b.jpg"], posed=False)
    cfg = compose_data("aachen", f"paths.data_dir={tmp_path}", f"data.ltvl_names._target_={__name__}.ShoutedNames")
    scene = scene_of(cfg.data)
    assert isinstance(scene.ltvl_names, ShoutedNames)
    write_ltvl(
        tmp_path / "out.txt", scene.queries.names, np.tile([1.0, 0, 0, 0], (2, 1)), np.zeros((2, 3)), scene.ltvl_names
    )
    assert [line.split()[0] for line in (tmp_path / "out.txt").read_text().splitlines()] == ["A.JPG", "B.JPG"]
    chosen = compose_data("aachen", f"paths.data_dir={tmp_path}", "data/ltvl_names=strip_prefix")
    assert scene_of(chosen.data).ltvl_names == WithoutFirstFolder()


@pytest.mark.parametrize("dataset", sorted(LAYOUTS))
def test_evaluate_runs_on_the_downloaders_layout(dataset, rendered, tmp_path):
    layout = LAYOUTS[dataset]
    install(layout, rendered, tmp_path / "data")
    cfg = helpers.evaluate_config(
        f"data={dataset}",
        f"paths.data_dir={tmp_path / 'data'}",
        f"paths.root_dir={tmp_path}",
        "model=precomputed",
        f"model.feature_name={layout.feature_name}",
        "paradigms.approximation.k=[1,3]",
        "paradigms.local_sfm.k=[3]",
        "paradigms.global_sfm.k=[1,3]",
        "sfm.workers=1",
        "report.figure_formats=[]",
        *UNREAD,
        *helpers.QUIET_EXTRACTION[:1],
    )
    output = tmp_path / "run"
    evaluate(cfg, output)
    ltvl = sorted(path.stem for path in (output / "ltvl" / layout.feature_name).glob("*.txt"))
    sfm = (
        [] if dataset == "inloc" else ["global_sfm_pnp_k1", "global_sfm_pnp_k3", "local_sfm_pnp_k3"]
    )  # InLoc: paradigm 1 only
    assert ltvl == sorted([f"approximation_{m}_k{k}" for m in ("bdi", "csi", "ewb") for k in (1, 3)] + sfm)
    for stem in ltvl:  # paradigm 1 poses every query; the SfM paradigms the ones they register
        lines = (output / "ltvl" / layout.feature_name / f"{stem}.txt").read_text().splitlines()
        assert len(lines) == 4 if stem.startswith("approximation") else len(lines) <= 4
    results = pd.read_csv(output / "results.csv")
    posed = sum(
        len(rows)
        for folder, rows in zip(layout.queries, split(4, len(layout.queries)))
        if folder in layout.posed_queries
    )
    assert (results.loc[results["subset"] == "all", "num_queries"] == posed).all()
    assert posed == 0 or set(results.loc[results["ranking"] == layout.feature_name, "paradigm"]) == {
        "approximation",
        "local_sfm",
        "global_sfm",
    }
    assert (output / "report.md").is_file()


def test_inloc_refuses_global_sfm_at_start_up(rendered, tmp_path):
    install(LAYOUTS["inloc"], rendered, tmp_path / "data")
    cfg = helpers.evaluate_config(
        "data=inloc",
        f"paths.data_dir={tmp_path / 'data'}",
        f"paths.root_dir={tmp_path}",
        "model=precomputed",
        "model.feature_name=AP-GeM-LM18",
        "paradigms.global_sfm.enabled=true",
    )
    with pytest.raises(
        ConfigError, match="dataset 'inloc' does not support global_sfm: InLoc's global map comes from its depth scans"
    ):
        evaluate(cfg, tmp_path / "run")
    assert not (tmp_path / ".cache").exists()  # refused before any work (nothing cached)


def test_a_dry_run_logs_the_plan_and_its_forecast_and_writes_nothing(rendered, tmp_path, caplog):
    install(LAYOUTS["baidu"], rendered, tmp_path / "data")
    scene = rendered[0]
    cfg = helpers.evaluate_config(
        "data=baidu",
        f"paths.data_dir={tmp_path / 'data'}",
        f"paths.root_dir={tmp_path}",
        "model=precomputed",
        "model.feature_name=densevlad_multi",
        "paradigms.local_sfm.k=[3]",
        "paradigms.global_sfm.k=[1,3]",
        "sfm.workers=1",
        "baselines.random=false",  # the random ranking is drawn, so counted exactly: here every ranking is bounded
        "dry_run=true",
        *helpers.QUIET_EXTRACTION[:1],
    )
    before = {path for path in tmp_path.rglob("*")}
    with caplog.at_level("INFO", logger="locretrieval"):
        assert evaluate(cfg, tmp_path / "run").empty
    plan = next(record.getMessage() for record in caplog.records if "SfM plan" in record.getMessage())
    # no output folder: the unit costs it measured, kept in the cache and named in its log, and nothing else
    [calibration] = re.findall(r"unit costs measured now and kept in (\S+\.npz) ", plan)
    written = {Path(calibration), Path(calibration).parent, tmp_path / ".cache"}
    assert {path for path in tmp_path.rglob("*")} == before | written
    # 4 rankings none of which is cached (the model, 3 ground truths), 12 database images, 4 queries, each
    # ranking's top 3 apart; the co-observation ground truth matches the global map's pairs and each query's
    # overlapping images first
    assert (
        "not computed yet, their work bounded: densevlad_multi, gt_relative_pose, gt_frustum, gt_co_observation;"
        in plan
    )
    rankings, queries, images = 4, 4, 12
    query_pairs = min(rankings * queries * 3, queries * images)
    selection = replace(helpers.sfm_settings().map_pairs, far=50.0, min_radius=10.0, max_per_image=None)
    map_pairs = len(database_pairs(scene.database, selection))
    joint = len(overlapping_pairs(scene.queries, scene.database, replace(selection, max_per_image=50), False))
    assert map_pairs > 0 and joint > 0 and "local features of 16 (16 new) images" in plan
    local_pairs = rankings * queries * 3
    assert (
        f"local_sfm: query pairs {query_pairs} ({min(query_pairs, queries * images - joint)} new), "
        f"database pairs {local_pairs} ({min(local_pairs, 66 - map_pairs)} new), "
        f"maps {rankings * queries} ({rankings * queries} new), registrations {rankings * queries}"
    ) in plan
    assert (
        f"global_sfm: query pairs {query_pairs} ({min(query_pairs, queries * images - joint)} new), "
        f"database pairs {map_pairs} (0 new), maps 1 (1 new), registrations {rankings * queries * 2}"
    ) in plan
    assert f"ground truth: pairs {map_pairs + joint} ({map_pairs + joint} new), matched first" in plan
    assert "calibrated in" in plan and "forecast: features" in plan and "(x0.5-2)" in plan
