"""Real datasets as NAVER's downloader installs them: for each dataset, a miniature of its folder
tree (kapture folders with the dataset's image naming, published global-feature names under
``<dataset>/global_features/<name>/global_features``, R2D2-named local features under
``<dataset>/local_features/r2d2_WASF-N8_20k/{keypoints,descriptors}``) built from a tiny rendered
scene, and ``evaluate.py data=<name> model=precomputed model.feature_name=<name>`` end to end."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import helpers
import numpy as np
import pandas as pd
import pytest
from helpers import evaluate
from published_layouts import LAYOUTS, SCENE, install, split

from locretrieval.build import scene_of
from locretrieval.config import ConfigError, built
from locretrieval.retrieval.pairs_file import FileOrder, PairOrder, PairsFileRanking, ScoreOrder
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset
from locretrieval.sfm.features import extract_features
from locretrieval.sfm.pairs import database_pairs, overlapping_pairs


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    root = tmp_path_factory.mktemp("published_source")
    render_synthetic_dataset(helpers.render_settings(SCENE), root)
    scene = load_kapture_scene("rendered", [root / "mapping"], [root / "query"])
    features = extract_features(scene.database, helpers.sfm_settings().features, root / "cache", 1)
    query_features = extract_features(scene.queries, helpers.sfm_settings().features, root / "cache", 1)
    local = {**features.load(scene.database.names), **query_features.load(scene.queries.names)}
    return scene, local


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


def test_a_pairs_order_from_outside_the_package_is_chosen_through_the_config(rendered, tmp_path, monkeypatch):
    install(LAYOUTS["baidu"], rendered, tmp_path / "data")
    common = ["data=baidu", f"paths.data_dir={tmp_path / 'data'}", f"paths.root_dir={tmp_path}", "model=pairs"]
    scene = scene_of(helpers.evaluate_config(*common, "model.path=unused").data)
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
