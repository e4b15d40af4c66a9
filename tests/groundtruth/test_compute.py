"""Ground truths computed as the config says (`locretrieval.groundtruth.compute`): definitions chosen
and switched off through Hydra, checked, cached; retrieval relevance; a definition from outside the package."""

import dataclasses
from typing import ClassVar

import helpers
import numpy as np
import pytest
from helpers import compose_config, evaluate_config
from posed_cameras import (
    NEAR,
    frustum_groundtruth,
    relative_pose_groundtruth,
)

from locretrieval import geometry
from locretrieval.config import ConfigError, validated
from locretrieval.groundtruth import (
    FrustumDefinition,
    RelativePoseDefinition,
    compute,
    compute_groundtruths,
)
from locretrieval.scene import Scene

FRUSTUM = {"_target_": "locretrieval.groundtruth.FrustumDefinition", "near": NEAR, "min_radius": 0.0}


def test_retrieval_relevance_is_that_of_the_top_depth_ranking_unless_all(pose_scene):
    from locretrieval.benchmark import relevances

    def scope(*overrides: str) -> compute.GroundTruthSettings:
        cfg = evaluate_config("paths.root_dir=/nonexistent", *overrides)
        return validated(compute.GroundTruthSettings, cfg.groundtruth, "groundtruth").relevance

    database, queries = pose_scene
    gt = relative_pose_groundtruth(database, queries, depth=2)  # query 0: relevant d0, d1, d4; top 2: d0, d4
    top = relevances({"rp": gt}, scope())["rp"]  # the default: configs/groundtruth/relevance/top_k.yaml
    assert top.dtype == bool and top.shape == gt.relevance.shape
    assert top[0].indices.tolist() == [0, 4] and top[1].nnz == 0 and top[2].nnz == 0  # the paper: reduced to the top k
    assert relevances({"rp": gt}, scope("groundtruth/relevance=all"))["rp"][0].indices.tolist() == [0, 1, 4]
    with pytest.raises(
        ConfigError,
        match=r"groundtruth.relevance: a RelevanceScope is chosen by its config group now: groundtruth/relevance=all",
    ):
        scope("groundtruth.relevance=all")


def test_compute_groundtruths_reads_the_default_config(pose_scene, tmp_path):
    cfg = evaluate_config("paths.root_dir=/nonexistent")  # configs/groundtruth/default.yaml and its definitions
    assert "co_observation" in cfg.groundtruth.enabled  # needs SfM settings; tested in test_co_observation
    cfg.groundtruth.enabled.remove("co_observation")
    database, queries = pose_scene
    scene = Scene("poses", database, queries, frustum_far=30.0)  # the frustum's far: null is the scene's
    groundtruths = compute_groundtruths(scene, cfg.groundtruth)
    assert list(groundtruths) == ["relative_pose", "frustum"]
    assert groundtruths["frustum"].name == "gt_frustum"
    direct = frustum_groundtruth(database, queries, far=30.0)
    np.testing.assert_array_equal(groundtruths["frustum"].ranking.indices, direct.ranking.indices)


def test_ground_truths_are_switched_off_and_picked_through_hydra(pose_scene):
    scene = Scene("poses", *pose_scene, frustum_far=30.0)

    def settings(*overrides: str) -> compute.GroundTruthSettings:
        cfg = evaluate_config("paths.root_dir=/nonexistent", *overrides)
        return validated(compute.GroundTruthSettings, cfg.groundtruth, "groundtruth")

    assert list(settings().definitions) == ["relative_pose", "frustum", "co_observation"]
    assert list(settings("groundtruth.definitions={}").definitions) == list(settings().definitions)  # merged by Hydra
    for off in ("groundtruth=none", "groundtruth.enabled=[]", "groundtruth.definitions=null"):
        assert compute_groundtruths(scene, settings(off)) == {}, off
    picked = settings("groundtruth.enabled=[frustum,relative_pose]")
    assert list(compute_groundtruths(scene, picked)) == ["frustum", "relative_pose"]
    variant = (
        "+groundtruth.definitions.frustum_25m="
        "{_target_: locretrieval.groundtruth.FrustumDefinition, near: 0.1, far: 25.0, min_radius: 0.0}"
    )  # the recipe of configs/groundtruth/default.yaml
    chosen = compute_groundtruths(scene, settings(variant, "groundtruth.enabled=[frustum_25m]"))
    assert list(chosen) == ["frustum_25m"]
    direct = frustum_groundtruth(*pose_scene, far=25.0)
    np.testing.assert_array_equal(chosen["frustum_25m"].ranking.indices, direct.ranking.indices)
    assert (chosen["frustum_25m"].relevance != direct.relevance).nnz == 0
    with pytest.raises(
        ConfigError, match=r"groundtruth.enabled: \['frustun'\] have no entry in groundtruth.definitions"
    ):
        settings("groundtruth.enabled=[frustum,frustun]")


def test_definition_types_and_errors(pose_scene):
    database, queries = pose_scene
    scene = Scene("poses", database, queries)
    config = helpers.groundtruth_section({"frustum_25m": {"far": 25.0, **FRUSTUM}}, depth=3)
    gt = compute_groundtruths(scene, config)["frustum_25m"]
    assert gt.name == "gt_frustum_25m" and gt.ranking.depth == 3
    with pytest.raises(ConfigError, match=r"groundtruth.definitions.coobs: must be a mapping with a _target_"):
        compute_groundtruths(scene, helpers.groundtruth_section({"coobs": {}}, depth=3))
    with pytest.raises(ConfigError, match=r"groundtruth.definitions.frustum: must be .* its parameters, not a type"):
        compute_groundtruths(scene, helpers.groundtruth_section({"frustum": {"type": "frustum", "far": 25.0}}, depth=3))
    with pytest.raises(
        ConfigError,
        match=r"groundtruth.definitions.frustum.farr: unknown key; expected one of \['near', 'far', 'min_radius'\]",
    ):
        compute_groundtruths(scene, helpers.groundtruth_section({"frustum": {"farr": 3, **FRUSTUM}}, depth=3))
    with pytest.raises(
        ConfigError, match=r"groundtruth.definitions.frustum.far is null .* scene 'poses' has no frustum_far"
    ):
        compute_groundtruths(scene, helpers.groundtruth_section({"frustum": {"far": None, **FRUSTUM}}, depth=3))
    with pytest.raises(ConfigError, match=r"groundtruth.depth: must be >= 1, got 0"):
        compute_groundtruths(scene, helpers.groundtruth_section({}, depth=0))


def test_cache_round_trip(pose_scene, tmp_path, monkeypatch):
    database, queries = pose_scene
    scene = Scene("poses", database, queries)
    relative_pose = {
        "_target_": "locretrieval.groundtruth.RelativePoseDefinition",
        "position_threshold": 25.0,
        "rotation_threshold": 45.0,
        "ranked": "within_thresholds",
    }
    config = helpers.groundtruth_section(
        {"relative_pose": relative_pose, "frustum": {"far": 40.0, **FRUSTUM}}, depth=50
    )
    first = compute_groundtruths(scene, config, cache_dir=tmp_path)
    files = sorted((tmp_path / "groundtruth").glob("*.npz"))
    assert len(files) == 2

    def not_again(*args, **kwargs):
        raise AssertionError("a cached ground truth was computed again")

    for kind in (RelativePoseDefinition, FrustumDefinition):
        monkeypatch.setattr(kind, "groundtruth", not_again)
    second = compute_groundtruths(scene, config, cache_dir=tmp_path)
    for name, gt in first.items():
        assert second[name].name == gt.name
        np.testing.assert_array_equal(second[name].ranking.indices, gt.ranking.indices)
        np.testing.assert_array_equal(second[name].ranking.scores, gt.ranking.scores)
        assert (second[name].relevance != gt.relevance).nnz == 0
        assert second[name].statistics() == gt.statistics()
    monkeypatch.undo()
    compute_groundtruths(
        scene, helpers.groundtruth_section({"frustum": {"far": 20.0, **FRUSTUM}}, depth=50), cache_dir=tmp_path
    )
    assert len(list((tmp_path / "groundtruth").glob("*.npz"))) == 3


@dataclasses.dataclass
class CameraDistance:
    """A ground-truth definition from outside the package: camera distance alone, relevant
    within ``radius`` metres, graded 1 - d / radius."""

    radius: float
    uses_sfm: ClassVar[bool] = False

    def distances(self, images, rows, others):
        return geometry.pairwise_position_errors(images.centers[rows], others.centers)

    def groundtruth(self, database, queries, depth, name, context):
        from locretrieval.groundtruth import groundtruth_from_scores

        def score_block(rows):
            distance = self.distances(queries, rows, database)
            return -distance, distance < self.radius, distance < self.radius

        return groundtruth_from_scores(name, database, queries, depth, score_block)

    def graded(self, images, context):
        def grade(rows):
            distance = self.distances(images, rows, images)
            return np.where(distance < self.radius, 1.0 - distance / self.radius, 0.0)

        return grade


OUTSIDE = f"{__name__}.CameraDistance"


def test_a_definition_from_outside_the_package_is_chosen_by_target_for_ranking_relevance_and_training(
    pose_scene, monkeypatch
):
    """A definition of this module, chosen through the config alone (its ``_target_``, no registry
    entry), ranks the benchmark's queries and grades training pairs."""
    from locretrieval.groundtruth import DefinitionContext, definition_type
    from locretrieval.training.relevance import TrainingRelevanceSettings, training_pairs

    database, queries = pose_scene
    node = f"{{_target_: {OUTSIDE}, radius: 12.0}}"
    cfg = evaluate_config(
        "paths.root_dir=/nonexistent", f"+groundtruth.definitions.near={node}", "groundtruth.enabled=[near]"
    )
    found = compute_groundtruths(Scene("poses", database, queries), cfg.groundtruth)
    distance = np.linalg.norm(
        queries.centers[:, None] - database.centers[None], axis=2
    )  # d0 10 m, d1 0, d2 20, d3 30, d4 5
    posed = queries.has_pose
    assert list(found) == ["near"]
    np.testing.assert_array_equal(found["near"].relevance.toarray()[posed], distance[posed] < 12.0)
    assert found["near"].ranking.indices[0, :3].tolist() == [1, 4, 0]

    train = compose_config(
        "train", "paths.root_dir=/nonexistent", "~train_relevance.definition", f"+train_relevance.definition={node}"
    )
    settings = validated(TrainingRelevanceSettings, train.train_relevance, "train_relevance")
    assert definition_type(settings.definition) == OUTSIDE
    graded = training_pairs(database, settings, DefinitionContext(far=25.0)).graded.toarray()
    between = np.linalg.norm(database.centers[:, None] - database.centers[None], axis=2)
    expected = np.where(between < 12.0, 1.0 - between / 12.0, 0.0)
    np.fill_diagonal(expected, 0.0)
    np.testing.assert_allclose(graded, expected)
    train.train_relevance.definition.radius = "far"
    with pytest.raises(
        ConfigError, match=r"train_relevance.definition.radius: Value 'far' of type 'str' could not be converted"
    ):
        validated(TrainingRelevanceSettings, train.train_relevance, "train_relevance")
    for target, message in (
        (f"{__name__}.Missing", r"cannot import"),
        ("locretrieval.scene.Camera", r"is not a ground-truth definition"),
    ):
        with pytest.raises(ConfigError, match=rf"groundtruth.definitions.near._target_: .*{message}"):
            compute_groundtruths(
                Scene("poses", database, queries), helpers.groundtruth_section({"near": {"_target_": target}}, depth=50)
            )
