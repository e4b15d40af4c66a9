"""Rankings read from pairs files (`locretrieval.retrieval.pairs_file`, ``model=pairs``) on a dataset's
miniature as NAVER's downloader installs it: the poses of the ranking they came from, a bad line
named, a pairs order from outside the package."""

import helpers
import numpy as np
import pytest
from helpers import evaluate
from published_layouts import LAYOUTS, install

from locretrieval.build import scene_of
from locretrieval.config import ConfigError, built
from locretrieval.retrieval.pairs_file import FileOrder, PairOrder, PairsFileRanking, ScoreOrder
from locretrieval.scene.kapture_io import load_kapture_scene


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
