"""scripts/shortlist_oracle.py: a ranking's top K re-ordered by relative pose, and paradigm 1 of it."""

import importlib.util

import helpers
import numpy as np
import pytest
from training_runs import SCENE

from locretrieval.groundtruth.relative_pose import relative_pose_groundtruth
from locretrieval.metrics.localization import localized
from locretrieval.paradigms.approximation import EqualWeights, approximate_poses
from locretrieval.retrieval.ranking import EMPTY, Ranking, random_ranking
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset

spec = importlib.util.spec_from_file_location(
    "shortlist_oracle", helpers.CONFIGS.parent / "scripts" / "shortlist_oracle.py"
)
script = importlib.util.module_from_spec(spec)
spec.loader.exec_module(script)
THRESHOLDS = [[0.5, 5.0], [5.0, 10.0]]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("oracle_scene")
    render_synthetic_dataset(helpers.render_settings(SCENE), root)
    return load_kapture_scene("tiny", [root / "mapping"], [root / "query"], frustum_far=25.0)


def test_the_top_k_is_sorted_by_pose_score_and_the_rest_kept():
    ranking = Ranking("d", np.array([[4, 2, 7, 0, 1], [3, 0, EMPTY, EMPTY, EMPTY]]), np.zeros((2, 5)), "descriptor")
    scores = np.array([[5.0, 0.1, 3.0, 9.0, 1.0, 0, 0, 2.0], [0.5, 0, 0, 0.7, 0, 0, 0, 0]])
    result = script.reordered(ranking, scores, 3)
    np.testing.assert_array_equal(result.indices, [[4, 7, 2, 0, 1], [0, 3, EMPTY, EMPTY, EMPTY]])


def test_reordering_the_whole_database_by_pose_is_the_relative_pose_ground_truth(scene):
    """The last rows against the library's relative-pose ground truth ranking every image, run
    through EWB here; the top 3 re-ordered among themselves leaves EWB over 3 as it was."""
    size = len(scene.database)
    ranking = random_ranking(len(scene.queries), size, size, seed=3)
    table = script.shortlist_table(scene, ranking, [3, size], 3, 25.0, 45.0, THRESHOLDS)
    truth = relative_pose_groundtruth(
        scene.database, scene.queries, depth=size, position_threshold=25.0, rotation_threshold=45.0, ranked="all"
    ).ranking
    estimate = approximate_poses(scene.database, truth, [3], {"ewb": EqualWeights()})[0]
    expected = 100 * localized(*estimate.errors(scene.queries.qvec, scene.queries.tvec), THRESHOLDS, True)[:, 0].mean(
        axis=1
    )
    np.testing.assert_allclose(table.loc["relative pose (whole database)"], expected)
    np.testing.assert_allclose(table.loc[f"top {size} by pose"], expected)
    np.testing.assert_allclose(table.loc["top 3 by pose"], table.loc["as ranked"])
    assert table.loc["as ranked"].iloc[-1] < expected[-1]  # a random ranking is below the ground truth on this scene
    assert list(table.columns) == ["0.5 m, 5 deg", "5 m, 10 deg"]


def test_the_database_against_itself_leaves_each_image_out(scene):
    """``--database``: the relative-pose row against EWB over each database image's three nearest
    other images, scored ``c / tau_c + R / tau_R`` here from the centres and the wxyz quaternions."""
    database = script.database_as_queries(scene)
    size = len(scene.database)
    centers, qvec = scene.database.centers, scene.database.qvec
    distance = np.linalg.norm(centers[:, None] - centers[None], axis=-1)
    angle = np.degrees(2 * np.arccos(np.clip(np.abs(qvec @ qvec.T), 0.0, 1.0)))
    score = distance / 25.0 + angle / 45.0
    np.fill_diagonal(score, np.inf)
    nearest = np.argsort(score, axis=1, kind="stable")[:, : size - 1]
    estimate = approximate_poses(
        scene.database, Ranking("n", nearest, np.zeros(nearest.shape), "groundtruth"), [3], {"ewb": EqualWeights()}
    )[0]
    expected = 100 * localized(*estimate.errors(qvec, scene.database.tvec), THRESHOLDS, True)[:, 0].mean(axis=1)
    rng = np.random.default_rng(4)
    others = np.array([[j for j in rng.permutation(size) if j != i] for i in range(size)])
    ranking = Ranking("shuffled", others, np.zeros(others.shape), "baseline")
    table = script.shortlist_table(database, ranking, [size - 1], 3, 25.0, 45.0, THRESHOLDS, exclude_self=True)
    np.testing.assert_allclose(table.loc["relative pose (whole database)"], expected)
    np.testing.assert_allclose(table.loc[f"top {size - 1} by pose"], expected)
    with_self = script.shortlist_table(database, ranking, [size - 1], 3, 25.0, 45.0, THRESHOLDS)
    assert with_self.loc["relative pose (whole database)"].iloc[-1] > expected[-1]  # each image its own first neighbour
