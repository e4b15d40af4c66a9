"""End to end (`locretrieval.evaluation`): `evaluate.py` on a tiny rendered scene, in-process and through
the Hydra CLI."""

import html
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from helpers import TINY_SCENE, evaluate, evaluate_config
from hydra import compose, initialize_config_dir

import locretrieval  # noqa: F401
from locretrieval.build import scene_of
from locretrieval.report.markdown import md_text
from locretrieval.retrieval import Ranking

ROOT = Path(__file__).resolve().parents[1]


KS = [1, 2, 5, 10]
#: What no test here reads, at a fraction of the default's work: a DenseVLAD vocabulary from 20,000
#: RootSIFTs in 10 iterations (its ranking is one of the table's rows whatever its quality; the
#: multirun's jobs read its descriptors from the cache, so they are given the same model) and 100
#: bootstrap resamples (the intervals are not checked; every table, figure and section is still written).
CHEAP = ["model.vocabulary_samples=20000", "model.kmeans_iterations=10", "metrics.uncertainty.resamples=100"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("evaluate")
    overrides = [f"paths.root_dir={root}", f"paradigms.approximation.k=[{','.join(map(str, KS))}]", *TINY_SCENE, *CHEAP]
    overrides.append("report.scene_view.enabled=false")  # the 3D view: no test here reads it (tests/report has its own)
    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=overrides)
    output = root / "run"
    evaluate(cfg, output)
    return root, output


RANKINGS = ("densevlad", "gt_relative_pose", "gt_frustum", "gt_co_observation", "random")


K_PER_PARADIGM = {
    "approximation": set(KS),
    "local_sfm": {5, 10, 20},
    "global_sfm": {1, 5, 10, 20, 50},
}  # 50 > 32 images: labelled 50


def expected_methods():
    approximation = {("approximation", "densevlad", m) for m in ("ewb", "bdi", "csi")}
    approximation |= {("approximation", r, "ewb") for r in RANKINGS[1:]}
    return approximation | {(p, r, "pnp") for p in ("local_sfm", "global_sfm") for r in RANKINGS}


@pytest.mark.slow
@pytest.mark.smoke
def test_result_table_has_one_row_per_paradigm_method_k_threshold_and_subset(run):
    _, output = run
    results = pd.read_csv(output / "results.csv")
    assert set(zip(results["paradigm"], results["ranking"], results["method"])) == expected_methods()
    for paradigm, ks in K_PER_PARADIGM.items():
        assert set(results.loc[results["paradigm"] == paradigm, "k"]) == ks, paradigm
    assert (results["k_effective"] == results["k"].clip(upper=32)).all()
    subsets = results["subset"].nunique()
    expected_rows = sum(len(K_PER_PARADIGM[p]) for p, _, _ in expected_methods()) * 3 * subsets
    assert len(results) == expected_rows
    assert results["localized_pct"].between(0, 100).all()
    assert (results.loc[results["subset"] == "all", "num_queries"] == 16).all()


@pytest.mark.smoke
def test_ground_truth_beats_random(run):
    _, output = run
    results = pd.read_csv(output / "results.csv")
    loose = results[(results["subset"] == "all") & (results["position_threshold_m"] == 5.0)]
    at_k1 = loose[(loose["paradigm"] == "approximation") & (loose["k"] == 1)].set_index("ranking")["localized_pct"]
    assert at_k1["gt_relative_pose"] > at_k1["random"]
    local_sfm = loose[(loose["paradigm"] == "local_sfm") & (loose["k"] == 5)].set_index("ranking")["localized_pct"]
    assert local_sfm["gt_co_observation"] > local_sfm["random"]


@pytest.mark.smoke
def test_run_writes_every_output(run):
    _, output = run
    for name in (
        "report.md",
        "query_errors.csv.gz",
        "retrieval.csv",
        "groundtruth_statistics.csv",
        "summary.json",
        "config.yaml",
    ):
        assert (output / name).is_file(), name
    errors = pd.read_csv(output / "query_errors.csv.gz", keep_default_na=False)
    assert len(errors) == sum(len(K_PER_PARADIGM[p]) for p, _, _ in expected_methods()) * 16
    failed = errors["position_error_m"] == ""
    assert (errors.loc[failed, "failure"] != "").all(), "every failed query carries its reason"
    ltvl = output / "ltvl" / "densevlad" / "approximation_csi_k5.txt"
    lines = ltvl.read_text().splitlines()
    assert len(lines) == 16 and all(len(line.split()) == 8 for line in lines)
    assert (
        "![synthetic_mall_approximation_ewb](figures/synthetic_mall_approximation_ewb.png)"
        in (output / "report.md").read_text()
    )
    # median errors: one row per ranking x paradigm x method x k, each the median of that slice of the per-query errors
    medians = pd.read_csv(output / "median_errors.csv")
    assert len(medians) == sum(len(K_PER_PARADIGM[p]) for p, _, _ in expected_methods())
    estimated = pd.read_csv(output / "query_errors.csv.gz")
    slice_ = estimated[
        (estimated["ranking"] == "gt_relative_pose") & (estimated["paradigm"] == "global_sfm") & (estimated["k"] == 5)
    ]
    row = medians[
        (medians["ranking"] == "gt_relative_pose") & (medians["paradigm"] == "global_sfm") & (medians["k"] == 5)
    ].iloc[0]
    assert row["median_position_error_m"] == pytest.approx(np.nanmedian(slice_["position_error_m"]))
    assert row["estimated_pct"] == pytest.approx(100 * slice_["failure"].isna().mean())


@pytest.mark.slow
def test_multirun_from_the_command_line(run):
    root, _ = run  # the scene and the descriptors are cached under root/.cache by the first run
    command = [
        sys.executable,
        str(ROOT / "evaluate.py"),
        "-m",
        f"paths.root_dir={root}",
        "paradigms.approximation.weights.csi.alpha=4,8",
        f"hydra.sweep.dir={root}/multirun",
        "baselines.random=false",
        "output.ltvl=false",
        "report.figure_formats=[]",  # the jobs' own reports without figures: report.py below draws them
        "report.scene_view.enabled=false",
        "paradigms.local_sfm.enabled=false",  # CSI's alpha is what the jobs differ by
        "paradigms.global_sfm.enabled=false",
        *TINY_SCENE,
        *CHEAP,  # the fixture's model: its cached descriptors are read, not computed again
    ]
    completed = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert completed.returncode == 0, completed.stderr[-3000:]
    runs = sorted((root / "multirun").glob("*/results.csv"))
    assert len(runs) == 2
    csi = [
        pd.read_csv(path.parent / "query_errors.csv.gz").query("method == 'csi' and k == 10")["position_error_m"]
        for path in runs
    ]
    assert len(csi[0]) == len(csi[1]) == 16 and not np.allclose(csi[0], csi[1], equal_nan=True)  # alpha changes CSI
    assert "descriptor cache hit for 'densevlad'" in completed.stderr + completed.stdout  # not described again
    report = subprocess.run(
        [
            sys.executable,
            str(ROOT / "report.py"),
            str(root / "multirun"),
            "--output",
            str(root / "report"),
            "--formats",
            "png",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert report.returncode == 0, report.stderr[-3000:]
    text = (root / "report" / "report.md").read_text()
    # CSI's interpolated poses change with alpha: densevlad is reported once per setting (as Markdown text)
    labels = [f"densevlad [paradigms.approximation.weights.csi.alpha={alpha}]" for alpha in (4, 8)]
    assert all(md_text(label) in text for label in labels)
    assert all(label in html.unescape((root / "report" / "report.html").read_text()) for label in labels)


SMALL_SCENE = [
    "data.render.width=96",
    "data.render.height=72",
    "data.render.num_database=8",
    "data.render.num_queries=2",
    "data.render.texture_size=64",
    "data.render.length=20.0",
    "data.render.workers=1",
]


def test_every_missing_input_is_named_in_one_error_before_any_work(tmp_path):
    missing, cache = tmp_path / "missing", tmp_path / "cache"
    paths = [f"paths.root_dir={tmp_path}", f"paths.cache_dir={cache}", *SMALL_SCENE]
    overrides = ["model=precomputed", f"model.path={missing}/AP-GeM-LM18", "sfm/features=kapture",
                 f"paradigms.global_sfm.colmap_model={missing}/sfm", "subsets.dynamic_masks=[maskrcnn]",
                 f"subsets.mask_sources.maskrcnn.weights={missing}/maskrcnn.pth"]  # fmt: skip
    with pytest.raises(FileNotFoundError) as error:
        evaluate(evaluate_config(*paths, *overrides), tmp_path / "run")
    message = str(error.value)
    scene = next(
        path for path in (cache / "synthetic").iterdir() if path.is_dir()
    )  # the rendered kapture folders: no local features
    expected = [f"{missing}/AP-GeM-LM18/global_features.txt", f"{missing}/sfm not found", f"{missing}/maskrcnn.pth",
                *(f"{scene / part}/reconstruction/{kind}/r2d2/{kind}.txt" for part in ("mapping", "query")
                  for kind in ("keypoints", "descriptors"))]  # fmt: skip
    assert message.startswith("7 missing input(s)") and all(path in message for path in expected), message
    assert sorted(path.name for path in cache.iterdir()) == ["synthetic"]  # no descriptor, feature or ground truth
    assert not (tmp_path / "run" / "results.csv").exists()
    weights = f"{missing}/Pitts30K_struct.mat"  # the model is built first: its weights named with their publisher
    with pytest.raises(FileNotFoundError, match=f"weight file not found: {weights}; download it(.|\n)*cvg-data.inf"):
        evaluate(evaluate_config(*paths, "model=netvlad", f"model.weights={weights}"), tmp_path / "run")


class CentreOracle:
    """A model from outside the package, not a descriptor: each query's database images by camera
    distance; it reads a ``marker`` file (an input of the run)."""

    def __init__(self, name: str, marker: str) -> None:
        self.name, self.marker = name, Path(marker)

    def missing_inputs(self, scene):
        return [] if self.marker.is_file() else [f"marker: {self.marker} not found"]

    def rankings(self, scene, search):
        distance = np.linalg.norm(scene.queries.centers[:, None] - scene.database.centers[None], axis=2)
        order = np.argsort(distance, axis=1, kind="stable")[:, : search.settings.depth]
        return [Ranking(self.name, order, -np.take_along_axis(distance, order, 1), "groundtruth")]


def test_a_model_from_outside_the_package_is_evaluated_through_the_config(tmp_path, monkeypatch):
    marker = tmp_path / "marker.txt"
    node = f"{{_target_: {__name__}.CentreOracle, name: oracle, marker: {marker}}}"
    cfg = evaluate_config(
        f"paths.root_dir={tmp_path}", *SMALL_SCENE, "~model", f"+model={node}", "groundtruth=none",
        "paradigms.local_sfm.enabled=false", "paradigms.global_sfm.enabled=false", "paradigms.approximation.k=[1]",
        "report.figure_formats=[]", "report.scene_view.enabled=false", "baselines.random=false",
        "metrics.uncertainty.resamples=100",  # the intervals are not checked here
    )  # fmt: skip
    with pytest.raises(FileNotFoundError, match=rf"1 missing input.*\n- model.marker: {marker} not found"):
        evaluate(cfg, tmp_path / "run")
    marker.write_text("here")
    evaluate(cfg, tmp_path / "run")
    saved = np.load(tmp_path / "run" / "rankings" / "oracle.npz")
    scene = scene_of(cfg.data)
    distance = np.linalg.norm(scene.queries.centers[:, None] - scene.database.centers[None], axis=2)
    np.testing.assert_array_equal(saved["indices"], np.argsort(distance, axis=1, kind="stable"))
    results = pd.read_csv(tmp_path / "run" / "results.csv")
    assert set(results["ranking"]) == {"oracle"} and set(results["method"]) == {"ewb"}


def test_the_summary_and_the_report_hold_each_sfm_stage_with_its_work_counted(run):
    """Each stage's seconds and work done, in its units: the global registrations are the distinct
    (query, top-k images) of every ranking and k, counted here from the saved rankings."""
    import json

    _, output = run
    summary = json.loads((output / "summary.json").read_text())
    stages = summary["SfM stages"]
    assert list(stages) == [
        "features",
        "match + verify",
        "local_sfm: triangulate",
        "local_sfm: register",
        "global_sfm: triangulate",
        "global_sfm: register",
    ]
    assert all(record["seconds"] >= 0 for record in stages.values())
    registrations = set()
    for path in (output / "rankings").glob("*.npz"):
        with np.load(path) as ranking:
            indices = ranking["indices"]
        for k in sorted(K_PER_PARADIGM["global_sfm"]):
            registrations |= {(q, tuple(sorted(i for i in row[:k] if i >= 0))) for q, row in enumerate(indices)}
    assert stages["global_sfm: register"] == {
        "seconds": stages["global_sfm: register"]["seconds"],
        "cpu_seconds": stages["global_sfm: register"]["cpu_seconds"],
        "done": len(registrations),
        "unit": "registrations",
    }
    # CPU time where work was done (the workers' included): each registration runs RANSAC
    assert stages["global_sfm: register"]["cpu_seconds"] > 0 and stages["match + verify"]["cpu_seconds"] > 0
    assert summary["descriptors CPU seconds"] > 0 and summary["ground truth CPU seconds"] > 0
    assert stages["global_sfm: triangulate"]["done"] == 1 and stages["global_sfm: triangulate"]["unit"] == "maps"
    report = (output / "report.md").read_text()
    assert "SfM stages: seconds of work" in report and "{'" not in report  # a table, no Python repr
