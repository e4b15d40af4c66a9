"""export.py's pairs files and descriptor files, read back: by ``model=pairs`` (the same rankings and
results as the run they came from), by ``model=precomputed`` (the same rankings), by kapture's own
reader and as hloc's ``pairs_from_retrieval`` reads them; and the names they hold, checked."""

import re

import h5py
import helpers
import kapture
import kapture.io.csv
import kapture.io.features
import numpy as np
import pandas as pd
import pytest
from helpers import HOSTILE_IMAGE, HOSTILE_MODEL, compose_config, evaluate, evaluate_config, export

from locretrieval.build import scene_of
from locretrieval.export.pairs import PairsSettings
from locretrieval.export.scene import DescriptorSettings, export_scene
from locretrieval.models.files.feature_io import export_global_features
from locretrieval.retrieval.descriptors import describe_scene
from locretrieval.retrieval.index import search
from locretrieval.retrieval.pairs_file import PairsFileRanking, ScoreOrder
from locretrieval.retrieval.ranking import Ranking
from locretrieval.scene import Camera, ImageSet, Scene
from locretrieval.scene.names import exported_name_problem

#: A small scene and a small random network: what is tested is what is written, not the model.
SCENE = [
    "data.render.width=96",
    "data.render.height=72",
    "data.render.num_database=20",
    "data.render.num_queries=8",
    "data.render.texture_size=64",
    "data.render.length=20.0",
    "data.render.workers=1",
    "data.render.seed=5",
    "groundtruth.enabled=[relative_pose]",
    "device=cpu",
]


NETWORK = [
    "model=timm",
    "model.name=test_resnet",
    "model.random_init=true",
    "model.max_side=96",
    "model.extraction.num_workers=0",
    "model.extraction.progress=false",
]


EVALUATION = [
    "paradigms.approximation.k=[1,3]",
    "paradigms.local_sfm.enabled=false",
    "paradigms.global_sfm.enabled=false",
    "baselines.random=false",
    "report.figure_formats=[]",
    "report.scene_view.enabled=false",
]


MODEL = "test_resnet_random-init"


K = 20  # = retrieval.depth, clamped to the 20 database images


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """An evaluation, then ``export.py`` with its defaults (pairs and descriptors, every format) of
    the same scene and model: ``(root, evaluation folder, export folder, scene)``."""
    root = tmp_path_factory.mktemp("exports")
    common = [*SCENE, *NETWORK, f"paths.root_dir={root}"]
    evaluate(evaluate_config(*common, *EVALUATION), root / "run")
    cfg = compose_config("export", *common)
    written = export(cfg, root / "export")
    assert len(written) == 8  # 2 rankings x 2 pairs files, 2 kapture feature folders, 2 hloc files
    return root, root / "run", root / "export", scene_of(cfg.data)


def test_pairs_files_read_back_give_the_rankings_and_results_of_the_run(exported):
    root, run, folder, scene = exported
    ranked = np.load(run / "rankings" / f"{MODEL}.npz")
    hloc, kapture_pairs = (
        folder / "hloc" / f"pairs-query-{MODEL}{K}.txt",
        folder / "kapture" / f"pairs_localization_{MODEL}_{K}.txt",
    )
    output = root / "pairs"
    evaluate(
        evaluate_config(*SCENE, f"paths.root_dir={root}", *EVALUATION, "model=pairs", f"model.path={hloc}"), output
    )
    np.testing.assert_array_equal(np.load(output / "rankings" / f"{hloc.stem}.npz")["indices"], ranked["indices"])
    results, again = pd.read_csv(run / "results.csv"), pd.read_csv(output / "results.csv")
    assert set(again["ranking"]) == {hloc.stem, "gt_relative_pose"} and set(again["method"]) == {
        "ewb"
    }  # no descriptors
    original = results[(results["ranking"] == MODEL) & (results["method"] == "ewb")]
    assert len(original) == 2 * 3 * results["subset"].nunique()  # k in (1, 3), three thresholds
    pd.testing.assert_frame_equal(
        again[again["ranking"] == hloc.stem].drop(columns="ranking").reset_index(drop=True),
        original.drop(columns="ranking").reset_index(drop=True),
    )
    # kapture's file holds the scores, exactly: read in score order, the same ranking
    read = PairsFileRanking(name="kapture", path=str(kapture_pairs), order=ScoreOrder()).ranking(scene, K)
    np.testing.assert_array_equal(read.indices, ranked["indices"])
    np.testing.assert_array_equal(read.scores, ranked["scores"])
    with open(kapture_pairs) as stream:  # as kapture-localization's get_pairs_from_file reads it
        rows = kapture.io.csv.table_from_file(stream)
    assert rows[0] == [
        scene.queries.names[0],
        scene.database.names[ranked["indices"][0, 0]],
        repr(float(ranked["scores"][0, 0])),
    ]
    assert len(rows) == (ranked["indices"] >= 0).sum()


def test_ground_truth_pairs_hold_the_ground_truth_ranking(exported):
    _, run, folder, scene = exported
    truth = np.load(run / "rankings" / "gt_relative_pose.npz")
    lines = (folder / "hloc" / f"pairs-query-gt_relative_pose{K}.txt").read_text().splitlines()
    expected = [
        f"{scene.queries.names[q]} {scene.database.names[i]}"
        for q in range(len(scene.queries))
        for i in truth["indices"][q]
        if i >= 0
    ]
    assert lines == expected


def test_descriptor_files_read_back_give_the_same_rankings(exported):
    _, run, folder, scene = exported
    ranked = np.load(run / "rankings" / f"{MODEL}.npz")
    features = [
        folder / "kapture" / part / "reconstruction" / "global_features" / MODEL for part in ("mapping", "query")
    ]
    hloc = [folder / "hloc" / f"global-feats-{MODEL}-{part}.h5" for part in ("db", "query")]
    for paths in (features, hloc):
        described = describe_scene(helpers.precomputed(path=[str(p) for p in paths]), scene, None)
        ranking = search(described.queries, described.database, K, "read back", 256)
        np.testing.assert_array_equal(ranking.indices, ranked["indices"])
        np.testing.assert_allclose(ranking.scores, ranked["scores"], atol=1e-6)


def test_descriptor_files_are_laid_out_as_kapture_and_hloc_read_them(exported):
    _, _, folder, scene = exported
    for part, images in (("mapping", scene.database), ("query", scene.queries)):
        kapture_dir = str(folder / "kapture" / part)
        features = kapture.io.csv.global_features_from_dir(MODEL, kapture_dir, None)
        assert sorted(features) == sorted(images.names) and features.dtype == np.float32
        vector = kapture.io.features.image_global_features_from_file(
            kapture.io.features.get_global_features_fullpath(MODEL, kapture_dir, images.names[0]),
            features.dtype,
            features.dsize,
        )
        assert np.linalg.norm(vector) == pytest.approx(1.0, abs=1e-5)
    for part, images in (("db", scene.database), ("query", scene.queries)):
        with h5py.File(folder / "hloc" / f"global-feats-{MODEL}-{part}.h5", "r") as file:
            names = []  # as hloc's list_h5_names: the parent group of every dataset
            file.visititems(
                lambda _, item: names.append(item.parent.name.strip("/")) if isinstance(item, h5py.Dataset) else None
            )
            assert sorted(names) == sorted(images.names)
            assert file[images.names[0]]["global_descriptor"].shape == (features.dsize,)


def tiny_scene(database: list[str], queries: list[str]) -> Scene:
    """A scene of these image names (no image files: nothing reads them)."""
    camera = Camera("PINHOLE", 8, 8, (4.0, 4.0, 4.0, 4.0))

    def images(names):
        return ImageSet(
            names, "/nonexistent", [camera] * len(names), [[1.0, 0, 0, 0]] * len(names), [[0.0] * 3] * len(names)
        )

    return Scene("tiny", images(database), images(queries))


def unit_rows(rows: int, seed: int) -> np.ndarray:
    values = np.random.default_rng(seed).normal(size=(rows, 4)).astype(np.float32)
    return values / np.linalg.norm(values, axis=1, keepdims=True)


def ranking_of(scene: Scene, name: str) -> Ranking:
    return search(unit_rows(len(scene.queries), 1), unit_rows(len(scene.database), 2), 2, name, 8)


EVERYTHING = (PairsSettings(["hloc", "kapture"], 2), DescriptorSettings(["kapture", "hloc"]))


def test_hostile_names_write_nothing_outside_the_export_folder(tmp_path):
    scene = tiny_scene(["db/a.png", "db/<b>.png", HOSTILE_IMAGE.replace("query/", "db/")], [HOSTILE_IMAGE, "q.png"])
    written = export_scene(scene, [ranking_of(scene, HOSTILE_MODEL)], tmp_path / "out", *EVERYTHING)
    files = [path for path in tmp_path.rglob("*") if path.is_file()]
    assert len(written) == 6 and files and all(path.is_relative_to(tmp_path / "out") for path in files)
    (hloc_pairs,) = (tmp_path / "out" / "hloc").glob("pairs-query-*.txt")  # the model's name made one file name
    assert hloc_pairs.read_text().splitlines()[0].split(" ")[0] == HOSTILE_IMAGE  # the scene's name, as it is


@pytest.mark.parametrize(
    ("name", "problem"),
    [
        ("../../escape.png", "has a '..' component"),
        ("/etc/passwd", "is absolute"),
        ("db/a b.png", "has whitespace"),
        ("db/a,b.png", "has a comma"),
        ("#db.png", "starts with '#'"),
        ("db//a.png", "has an empty or '.' path component"),
        ("db/./a.png", "has an empty or '.' path component"),
        ("db\\a.png", "has a backslash"),
        ("db/a\n.png", "has a backslash or a control character"),
    ],
)
def test_a_name_the_exports_cannot_write_stops_the_export_before_any_file(tmp_path, name, problem):
    assert problem in exported_name_problem(name)
    for database, queries in (([name, "db/b.png"], ["q.png"]), (["db/b.png", "db/c.png"], [name])):
        scene = tiny_scene(database, queries)
        with pytest.raises(ValueError, match=re.escape(f"image name {name!r} {problem}")):
            export_scene(scene, [ranking_of(scene, "model")], tmp_path / "out", *EVERYTHING)
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match=re.escape(problem)):
        export_global_features([name], unit_rows(1, 0), tmp_path / "kapture", "model")
    assert not (tmp_path / "kapture").exists() or not any((tmp_path / "kapture").rglob("*.gfeat"))


def test_a_link_leading_out_of_the_feature_folder_is_not_followed(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    folder = tmp_path / "kapture" / "reconstruction" / "global_features" / "model"
    folder.mkdir(parents=True)
    (folder / "db").symlink_to(outside)
    with pytest.raises(ValueError, match="leads outside"):
        export_global_features(["db/a.png"], unit_rows(1, 0), tmp_path / "kapture", "model")
    assert not any(outside.iterdir())
