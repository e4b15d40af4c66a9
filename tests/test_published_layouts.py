"""Real datasets as NAVER's downloader installs them: for each dataset, a miniature of its folder
tree (kapture folders with the dataset's image naming, published global-feature names under
``<dataset>/global_features/<name>/global_features``, R2D2-named local features under
``<dataset>/local_features/r2d2_WASF-N8_20k/{keypoints,descriptors}``) built from a tiny rendered
scene, and ``evaluate.py data=<name> model=precomputed model.feature_name=<name>`` end to end."""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import helpers
import kapture
import kapture.io.csv as kapture_csv
import numpy as np
import pandas as pd
import pytest
from PIL import Image

from locretrieval.config import ConfigError, built
from locretrieval.evaluation import evaluate
from locretrieval.retrieval.pairs_file import FileOrder, PairOrder, PairsFileRanking, ScoreOrder
from locretrieval.scene import ImageSet
from locretrieval.scene.datasets import instantiate_scene
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset
from locretrieval.sfm.features import extract_features
from locretrieval.sfm.pairs import database_pairs

SCENE = {"width": 192, "height": 144, "num_database": 12, "num_queries": 4, "texture_size": 64, "length": 20.0,
         "conditions": {"night": 0.0, "blur": 0.0, "dynamic": 0.0, "noise": 0.0}, "database_dynamic": 0.0,
         "hard_query_fraction": 0.0, "workers": 1, "seed": 4}  # fmt: skip
R2D2 = "r2d2_WASF-N8_20k"
GLOBAL_DIMENSION = 48


@dataclass(frozen=True)
class Layout:
    """Where a dataset's kapture folders and features are, relative to the data root:
    ``mapping``/``queries`` folders with the image names they get (``{i}``: a counter),
    which query folders have poses, the folder holding ``global_features``/``local_features``
    for each kapture folder, and where the images are when the kapture folders link their
    ``records_data`` there (RobotCar v1, published without images)."""

    mapping: dict[str, str]
    queries: dict[str, str]
    posed_queries: tuple[str, ...]
    feature_name: str
    shared_images: str | None = None

    def feature_root(self, folder: str) -> str:
        return str(Path(folder).parent)


LAYOUTS = {
    "aachen": Layout(
        {"Aachen-Day-Night-v1.1/mapping": "db/{i}.jpg"},
        {
            "Aachen-Day-Night-v1.1/query_day": "query/day/milestone/2010-10-30_17-47-25_{i}.jpg",
            "Aachen-Day-Night-v1.1/query_night": "query/night/nexus5x/IMG_20161227_19{i:04d}.jpg",
        },
        (),
        "AP-GeM-LM18",
    ),
    "baidu": Layout(
        {"baidu-mall/mapping": "training_images_undistort/00/nikon5300a_{i:04d}.jpg"},
        {"baidu-mall/query": "query_images_undistort/cdm/cdm_20150523_10{i:04d}.jpg"},
        ("baidu-mall/query",),
        "densevlad_multi",
    ),
    "robotcar": Layout(
        {"RobotCar_Seasons-v1/mapping": "overcast-reference/rear/14171765{i:08d}.jpg"},
        {"RobotCar_Seasons-v1/query": "night/rear/14184{i:08d}.jpg"},
        ("RobotCar_Seasons-v1/query",),
        "netvlad_vd16pitts",
        shared_images="RobotCar_Seasons-v2/all/sensors/records_data",
    ),
    "robotcar_v2": Layout(
        {
            "RobotCar_Seasons-v2/01/mapping": "overcast-reference/rear/14171765{i:08d}.jpg",
            "RobotCar_Seasons-v2/02/mapping": "overcast-reference/rear/14171766{i:08d}.jpg",
        },
        {
            "RobotCar_Seasons-v2/01/query": "night/rear/14184{i:08d}.jpg",
            "RobotCar_Seasons-v2/02/query": "dawn/rear/14168{i:08d}.jpg",
        },
        (),
        "netvlad_vd16pitts",
    ),
    "gangnam": Layout(
        {"GangnamStation/B2/release/mapping": "10004/images/{i:06d}.jpg"},
        {
            "GangnamStation/B2/release/validation": "10005/images/{i:06d}.jpg",
            "GangnamStation/B2/release/test": "10006/images/{i:06d}.jpg",
        },
        ("GangnamStation/B2/release/validation",),
        "DELG",
    ),
    "inloc": Layout(
        {"InLoc/mapping": "DUC1/024/DUC_cutout_024_{i}_0.jpg"},
        {"InLoc/query": "iphone7/IMG_{i:04d}.JPG"},
        (),
        "AP-GeM-LM18",
    ),
}


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    root = tmp_path_factory.mktemp("published_source")
    render_synthetic_dataset(helpers.render_settings(SCENE), root)
    scene = load_kapture_scene("rendered", [root / "mapping"], [root / "query"])
    features = extract_features(scene.database, helpers.sfm_settings().features, root / "cache", 1)
    query_features = extract_features(scene.queries, helpers.sfm_settings().features, root / "cache", 1)
    local = {**features.load(scene.database.names), **query_features.load(scene.queries.names)}
    return scene, local


def split(count: int, parts: int) -> list[np.ndarray]:
    return np.array_split(np.arange(count), parts)


def write_kapture_folder(root: Path, images: ImageSet, rows: np.ndarray, pattern: str, posed: bool) -> dict[str, str]:
    """A kapture folder of ``images[rows]`` renamed by ``pattern`` and saved as JPEG, written by
    the kapture library; returns new name -> source name."""
    data = kapture.Kapture(
        sensors=kapture.Sensors(),
        records_camera=kapture.RecordsCamera(),
        trajectories=kapture.Trajectories() if posed else None,
    )
    names = {}
    for timestamp, row in enumerate(rows):
        camera = images.cameras[row]
        sensor = f"cam{timestamp}"
        data.sensors[sensor] = kapture.Camera(camera.model, [camera.width, camera.height, *camera.params])
        name = pattern.format(i=timestamp)
        data.records_camera[(timestamp, sensor)] = name
        if posed:
            data.trajectories[(timestamp, sensor)] = kapture.PoseTransform(
                r=images.qvec[row].tolist(), t=images.tvec[row].tolist()
            )
        path = root / "sensors" / "records_data" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.open(images.paths[row]).convert("RGB").save(path, quality=95)
        names[name] = images.names[row]
    kapture_csv.kapture_to_dir(str(root), data)
    return names


def write_features(
    feature_root: Path, feature_name: str, names: dict[str, str], local: dict, images: dict[str, Path]
) -> None:
    """Global features (a unit thumbnail per image) and the local features as R2D2 files, in the
    downloader's layout under ``feature_root``."""
    global_folder = feature_root / "global_features" / feature_name / "global_features"
    keypoints_folder = feature_root / "local_features" / R2D2 / "keypoints"
    descriptors_folder = feature_root / "local_features" / R2D2 / "descriptors"
    headers = {
        global_folder / "global_features.txt": f"{feature_name}, float32, {GLOBAL_DIMENSION}, L2",
        keypoints_folder / "keypoints.txt": f"{R2D2}, float32, 2",
        descriptors_folder / "descriptors.txt": f"{R2D2}, float32, 128, {R2D2}, L2",
    }
    for path, line in headers.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(f"# kapture format: 1.1\n{line}\n")
    for name, source in names.items():
        thumbnail = np.asarray(Image.open(images[source]).convert("L").resize((8, 6)), dtype=np.float32).ravel()
        thumbnail -= thumbnail.mean()
        keypoints, descriptors = local[source]
        arrays = {
            global_folder / f"{name}.gfeat": thumbnail / np.linalg.norm(thumbnail),
            keypoints_folder / f"{name}.kpt": keypoints - 0.5,  # R2D2's pixel centres start at (0, 0)
            descriptors_folder / f"{name}.desc": descriptors / np.linalg.norm(descriptors, axis=1, keepdims=True),
        }
        for path, array in arrays.items():
            path.parent.mkdir(parents=True, exist_ok=True)
            np.ascontiguousarray(array, dtype=np.float32).tofile(path)


def install(layout: Layout, rendered, data_dir: Path) -> None:
    scene, local = rendered
    sources = {
        **dict(zip(scene.database.names, scene.database.paths)),
        **dict(zip(scene.queries.names, scene.queries.paths)),
    }
    groups = [
        (folder, pattern, scene.database, rows, True)
        for (folder, pattern), rows in zip(layout.mapping.items(), split(len(scene.database), len(layout.mapping)))
    ]
    groups += [
        (folder, pattern, scene.queries, rows, folder in layout.posed_queries)
        for (folder, pattern), rows in zip(layout.queries.items(), split(len(scene.queries), len(layout.queries)))
    ]
    for folder, pattern, images, rows, posed in groups:
        names = write_kapture_folder(data_dir / folder, images, rows, pattern, posed)
        write_features(data_dir / layout.feature_root(folder), layout.feature_name, names, local, sources)
        if layout.shared_images:
            records = data_dir / folder / "sensors" / "records_data"
            shutil.copytree(records, data_dir / layout.shared_images, dirs_exist_ok=True)
            shutil.rmtree(records)
            records.symlink_to(os.path.relpath(data_dir / layout.shared_images, records.parent))


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
        "dry_run=true",
        *helpers.QUIET_EXTRACTION[:1],
    )
    before = {path for path in tmp_path.rglob("*")}
    with caplog.at_level("INFO", logger="locretrieval"):
        assert evaluate(cfg, tmp_path / "run").empty
    assert {path for path in tmp_path.rglob("*")} == before  # no output folder, no cache: nothing but the log
    plan = next(record.getMessage() for record in caplog.records if "SfM plan" in record.getMessage())
    # 5 rankings (the model, 3 ground truths, random), 12 database images, 4 queries, each ranking's top 3 apart
    rankings, queries, images = 5, 4, 12
    query_pairs = min(rankings * queries * 3, queries * images)
    map_pairs = len(
        database_pairs(
            scene.database, replace(helpers.sfm_settings().map_pairs, far=50.0, min_radius=10.0, max_per_image=None)
        )
    )
    assert map_pairs > 0 and "local features of 16 (16 new) images" in plan
    assert (
        f"local_sfm: query pairs {query_pairs} ({query_pairs} new), "
        f"database pairs {rankings * queries * 3} ({rankings * queries * 3} new), "
        f"maps {rankings * queries} ({rankings * queries} new) (~3 pairs each), registrations {rankings * queries}"
    ) in plan
    assert (
        f"global_sfm: query pairs {query_pairs} ({query_pairs} new), "
        f"database pairs {map_pairs} ({map_pairs} new), maps 1 (1 new)"
        f" (~{map_pairs} pairs each), registrations {rankings * queries * 2}"
    ) in plan
    assert "matching on cpu" in plan and "forecast: features" in plan and "at most" in plan


def test_rankings_from_pairs_files_give_the_poses_of_the_ranking_they_came_from(rendered, tmp_path):
    """The reference tools' pairs format (``query, db, score``, a ``#`` header) and hloc's
    (``query db``), written from the precomputed descriptors' ranking, give its EWB poses."""
    install(LAYOUTS["baidu"], rendered, tmp_path / "data")
    common = (
        "data=baidu",
        f"paths.data_dir={tmp_path / 'data'}",
        f"paths.root_dir={tmp_path}",
        "paradigms.approximation.k=[1,3]",
        "paradigms.local_sfm.enabled=false",
        "paradigms.global_sfm.enabled=false",
        "groundtruth=none",
        "baselines.random=false",
        "report.figure_formats=[]",
        *helpers.QUIET_EXTRACTION[:1],
    )
    evaluate(
        helpers.evaluate_config(*common, "model=precomputed", "model.feature_name=densevlad_multi"),
        tmp_path / "descriptor",
    )
    ranked = np.load(tmp_path / "descriptor" / "rankings" / "densevlad_multi.npz")
    scene = load_kapture_scene(
        "baidu", [tmp_path / "data" / "baidu-mall" / "mapping"], [tmp_path / "data" / "baidu-mall" / "query"]
    )
    rows = [
        (scene.queries.names[q], scene.database.names[i], float(s))
        for q in range(len(scene.queries))
        for i, s in zip(ranked["indices"][q], ranked["scores"][q])
        if i >= 0
    ]
    reference, hloc = tmp_path / "pairs_localization_3.txt", tmp_path / "pairs-query-densevlad3.txt"
    reference.write_text(
        "# query_image, map_image, score\n" + "".join(f"{q}, {d}, {s}\n" for q, d, s in reversed(rows))
    )
    hloc.write_text("".join(f"{q} {d}\n" for q, d, _ in rows))
    expected = {
        k: (tmp_path / "descriptor" / "ltvl" / "densevlad_multi" / f"approximation_ewb_k{k}.txt").read_text()
        for k in (1, 3)
    }
    for path, order in ((reference, "score"), (hloc, "file")):
        output = tmp_path / path.stem
        evaluate(helpers.evaluate_config(*common, "model=pairs", f"model.path={path}", f"model/order={order}"), output)
        ltvl = output / "ltvl" / path.stem
        assert sorted(p.name for p in ltvl.iterdir()) == [
            "approximation_ewb_k1.txt",
            "approximation_ewb_k3.txt",
        ]  # no descriptors: EWB only
        for k in (1, 3):
            assert (ltvl / f"approximation_ewb_k{k}.txt").read_text() == expected[k]
        np.testing.assert_array_equal(np.load(output / "rankings" / f"{path.stem}.npz")["indices"], ranked["indices"])


def test_a_bad_pairs_file_is_refused_naming_its_line(rendered, tmp_path):
    install(LAYOUTS["baidu"], rendered, tmp_path / "data")
    scene = load_kapture_scene(
        "baidu", [tmp_path / "data" / "baidu-mall" / "mapping"], [tmp_path / "data" / "baidu-mall" / "query"]
    )
    query, image = scene.queries.names[0], scene.database.names[0]
    cases = {
        f"{query} {image}\n{query}\n": r"pairs.txt:2: expected 'query database' or 'query, database, score'",
        f"{query}, {image}, high\n": r"pairs.txt:1: score 'high' is not a number",
        f"# header\n{image}, {image}, 0.5\n": r"pairs.txt:2: .* is a database image, not a query",
        f"{query} {image}\n{query} nowhere.jpg\n": r"pairs.txt:2: 'nowhere.jpg' is not a database image",
        f"{query} {image}\n{query} {image}\n": r"pairs.txt:2: pair .* repeats line 1",
    }
    path = tmp_path / "pairs.txt"
    for text, message in cases.items():
        path.write_text(text)
        with pytest.raises(ValueError, match=message):
            PairsFileRanking(name="pairs", path=str(path), order=FileOrder()).ranking(scene, 50)
    path.write_text(f"{query} {image}\n")
    with pytest.raises(ConfigError, match=r"model.order \(ScoreOrder\): .*pairs.txt:1 has no score"):
        PairsFileRanking(name="pairs", path=str(path), order=ScoreOrder()).ranking(scene, 50)
    ranking = PairsFileRanking(name="pairs", path=str(path), order=FileOrder()).ranking(
        scene, 50
    )  # the other queries: empty rankings
    assert ranking.indices[0, 0] == 0 and (ranking.indices[1:] == -1).all() and not ranking.has_descriptors
    cfg = helpers.evaluate_config(
        "data=baidu",
        f"paths.data_dir={tmp_path / 'data'}",
        f"paths.root_dir={tmp_path}",
        "model=pairs",
        f"model.path={tmp_path / 'absent.txt'}",
    )
    assert cfg.model.name == "absent"
    with pytest.raises(FileNotFoundError, match=r"model.path: pairs file .*absent.txt not found"):
        evaluate(cfg, tmp_path / "run")


class ReversedOrder(PairOrder):
    """A pairs order from outside the package: each query's pairs last first."""

    def arranged(self, rows, path):
        return {query: ranked[::-1] for query, ranked in rows.items()}


def test_a_pairs_order_from_outside_the_package_is_chosen_through_the_config(rendered, tmp_path):
    install(LAYOUTS["baidu"], rendered, tmp_path / "data")
    common = ["data=baidu", f"paths.data_dir={tmp_path / 'data'}", f"paths.root_dir={tmp_path}", "model=pairs"]
    scene = instantiate_scene(helpers.evaluate_config(*common, "model.path=unused").data)
    path = tmp_path / "pairs.txt"
    path.write_text(
        "".join(f"{query} {image}\n" for query in scene.queries.names for image in scene.database.names[:3])
    )
    cfg = helpers.evaluate_config(*common, f"model.path={path}", f"model.order._target_={__name__}.ReversedOrder")
    model = built(cfg.model, "model")
    assert isinstance(model.order, ReversedOrder) and model.missing_inputs(scene) == []
    np.testing.assert_array_equal(model.ranking(scene, 50).indices[:, :3], np.tile([2, 1, 0], (len(scene.queries), 1)))
    with pytest.raises(
        ConfigError, match=r"model.order: a PairOrder is chosen by its config group now: model/order=score"
    ):
        built(helpers.evaluate_config(*common, f"model.path={path}", "model.order=score").model, "model")
