"""Co-observation ground truth: shared 3D points of a joint map, checked against rendered depth."""

import helpers
import kapture.io.records as kapture_records
import numpy as np
import pytest
from scipy.stats import spearmanr

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.config import ConfigError
from locretrieval.frusta import TruncatedFrusta, pairwise_overlap_radii
from locretrieval.groundtruth import DefinitionContext, compute_groundtruths, frustum_groundtruth
from locretrieval.groundtruth.co_observation import co_observation_groundtruth, database_co_observations, shared_points
from locretrieval.paradigms.global_sfm import global_map
from locretrieval.retrieval import EMPTY
from locretrieval.scene import ImageSet, Scene
from locretrieval.sfm import matching
from locretrieval.sfm import pairs as pairs_module
from locretrieval.sfm.features import extract_features
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.pairs import PairSelection, database_pairs, overlapping_pairs
from locretrieval.training.relevance import TrainingRelevanceSettings, UnrelatedNegatives, training_pairs

SCENE = {
    "width": 256,
    "height": 192,
    "num_database": 40,
    "num_queries": 8,
    "texture_size": 128,
    "length": 20.0,
    "conditions": {"night": 0.0, "blur": 0.0, "dynamic": 0.0, "noise": 0.0},
    "database_dynamic": 0.0,
    "hard_query_fraction": 0.0,
    "workers": 1,
    "seed": 2,
}
PAIRS = {"near": 0.1, "far": 25.0, "min_radius": 0.0, "max_per_image": 10}  # the scene has no frustum_far
SFM = helpers.sfm_settings({"map_pairs": PAIRS})
COOBS = {"min_shared": 1, "query_pairs": 10, "sfm": SFM}
CO_OBSERVATION = "locretrieval.groundtruth.CoObservationDefinition"


def selection(**overrides) -> PairSelection:
    return PairSelection(**{**PAIRS, **overrides})


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return helpers.rendered_scene(tmp_path_factory.mktemp("co_observation_scene"), SCENE)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("co_observation_cache")


@pytest.fixture(scope="module")
def shared(scene, cache):
    return shared_points(scene.database, scene.queries, cache, SFM, 10).toarray()


def depth_map(images: ImageSet, index: int) -> np.ndarray:
    camera = images.cameras[index]
    return kapture_records.depth_map_from_file(str(images.depth_paths[index]), (camera.width, camera.height))


def covisible_keypoints(scene, cache) -> np.ndarray:
    """``[Q, N]``: query keypoints whose rendered surface point is also seen by database image t
    (projects inside it, in front, at the depth it renders there), from depth maps alone."""
    database, queries = scene.database, scene.queries
    keypoints = extract_features(queries, SFM.features, cache, 1).keypoints(queries.names)
    depths = [depth_map(database, t) for t in range(len(database))]
    counts = np.zeros((len(queries), len(database)), dtype=np.int64)
    for q, name in enumerate(queries.names):
        pixels = keypoints[name]
        z = depth_map(queries, q)[pixels[:, 1].astype(int), pixels[:, 0].astype(int)]
        rays = (
            np.column_stack([pixels, np.ones(len(pixels))]) @ np.linalg.inv(queries.cameras[q].calibration_matrix()).T
        )
        world = (rays * z[:, None] - queries.tvec[q]) @ geometry.quaternion_to_matrix(queries.qvec[q])
        for t, depth in enumerate(depths):
            camera = database.cameras[t]
            local = world @ geometry.quaternion_to_matrix(database.qvec[t]).T + database.tvec[t]
            projected = local @ camera.calibration_matrix().T
            uv = projected[:, :2] / projected[:, 2:]
            inside = (local[:, 2] > 0.1) & (uv >= 0).all(1) & (uv[:, 0] < camera.width) & (uv[:, 1] < camera.height)
            rendered = depth[uv[inside, 1].astype(int), uv[inside, 0].astype(int)]
            counts[q, t] = np.sum(np.abs(rendered - local[inside, 2]) < 0.05 * local[inside, 2])
    return counts


def test_shared_points_agree_with_covisibility_by_depth(scene, cache, shared):
    covisible = covisible_keypoints(scene, cache)
    assert shared.sum() > 100
    # a shared point is one query keypoint whose point the database image sees: a pair can
    # share no more points than it has covisible keypoints, up to a few wrong matches (on
    # repeated textures); covisibility also counts views too different for SIFT to match
    sharing = shared > 0
    excess = shared - covisible
    assert (excess[sharing] > 2).mean() < 0.05 and (excess <= 5).all()
    assert (covisible[shared >= 5] >= 5).all()
    # the scores rank pairs like covisibility does
    assert spearmanr(shared.ravel(), covisible.ravel()).statistic > 0.5
    # every query shares points with one of its most covisible images
    best = np.argsort(-covisible, axis=1)[:, :3]
    assert all(shared[q, best[q]].max() > 0 for q in range(len(shared)))


def test_groundtruth_ranks_by_shared_points_chosen_by_target(scene, cache, shared, monkeypatch):
    database, queries = scene.database, scene.queries
    scene = Scene("tiny", database, queries)
    config = helpers.groundtruth_section(
        {"coobs": {"_target_": CO_OBSERVATION, "min_shared": 5, "query_pairs": 10}}, depth=10
    )
    groundtruth = compute_groundtruths(scene, config, SFM, cache_dir=cache)["coobs"]
    assert groundtruth.name == "gt_coobs" and groundtruth.ranking.kind == "groundtruth"
    indices, scores = groundtruth.ranking.indices, groundtruth.ranking.scores
    for q in range(len(queries)):
        ranked = indices[q][indices[q] != EMPTY]
        np.testing.assert_array_equal(scores[q, : len(ranked)], shared[q, ranked])
        assert (np.diff(scores[q, : len(ranked)]) <= 0).all()
        assert len(ranked) == min(10, int((shared[q] > 0).sum()))
    np.testing.assert_array_equal(groundtruth.relevance.toarray(), shared >= 5)
    statistics = groundtruth.statistics()
    assert statistics["avg_relevant"] == pytest.approx((shared >= 5).sum(1).mean())
    again = compute_groundtruths(scene, config, SFM, cache_dir=cache)["coobs"]  # the cached ground truth
    np.testing.assert_array_equal(again.ranking.indices, indices)
    # the joint map again: its matches are read from the cache, nothing is matched again
    calls = []
    real = matching.NearestNeighbourMatcher.__call__
    monkeypatch.setattr(matching.NearestNeighbourMatcher, "__call__", lambda *args: calls.append(1) or real(*args))
    recomputed = shared_points(database, queries, cache, SFM, 10)
    np.testing.assert_array_equal(recomputed.toarray(), shared)
    assert not calls
    with pytest.raises(ConfigError, match=r"groundtruth.definitions.co_observation.min_shard: unknown key"):
        compute_groundtruths(
            scene,
            helpers.groundtruth_section(
                {"co_observation": {"_target_": CO_OBSERVATION, "min_shard": 1, "query_pairs": 10}}, depth=10
            ),
            SFM,
        )
    with pytest.raises(
        ConfigError,
        match=r"groundtruth.definitions.co_observation: locretrieval.*CoObservationDefinition needs the sfm",
    ):
        definition = {"_target_": CO_OBSERVATION, "min_shared": 1, "query_pairs": 10}
        compute_groundtruths(scene, config | {"definitions": {"co_observation": definition}})


def test_queries_without_a_pose_get_no_ranking_and_share_the_caches(scene, tmp_path):
    database, queries = scene.database, scene.queries
    qvec = queries.qvec.copy()
    qvec[0] = np.nan
    unposed = ImageSet(
        queries.names, queries.image_root, queries.cameras, qvec, queries.tvec, queries.tags, queries.depth_paths
    )
    groundtruth = co_observation_groundtruth(database, unposed, depth=5, cache_dir=tmp_path, **COOBS)
    assert (groundtruth.ranking.indices[0] == EMPTY).all() and not groundtruth.query_has_pose[0]
    assert (groundtruth.ranking.indices[1:, 0] != EMPTY).all()
    # the features (and raw matches) of all queries, as the SfM paradigms extract them: no second folder
    query_features = extract_features(queries, SFM.features, tmp_path, 1).folder
    database_features = extract_features(database, SFM.features, tmp_path, 1).folder
    assert sorted((tmp_path / "features").iterdir()) == sorted([query_features, database_features])
    raw_query_matches = [
        p
        for p in (tmp_path / "matches").iterdir()
        if p.name.startswith(query_features.name) and "--poses-" not in p.name
    ]
    assert len(raw_query_matches) == 1
    # without cache_dir: a temporary one, the same ground truth
    temporary = co_observation_groundtruth(database, unposed, depth=5, **COOBS)
    np.testing.assert_array_equal(temporary.ranking.indices, groundtruth.ranking.indices)
    with pytest.raises(ValueError, match="min_shared: must be >= 1"):
        co_observation_groundtruth(database, queries, depth=5, cache_dir=tmp_path, **{**COOBS, "min_shared": 0})


def test_frustum_pairs_are_the_same_chunk_by_chunk(scene, monkeypatch):
    database, queries = scene.database, scene.queries
    settings = selection(max_per_image=4, min_radius=0.5)
    whole = [overlapping_pairs(queries, database, settings, exclude_self=False), database_pairs(database, settings)]
    assert len(whole[0]) and len(whole[1])
    monkeypatch.setattr(pairs_module, "PAIRS_PER_CHUNK", 3 * len(database))  # three rows at a time
    chunked = [overlapping_pairs(queries, database, settings, exclude_self=False), database_pairs(database, settings)]
    for expected, found in zip(whole, chunked):
        np.testing.assert_array_equal(found, expected)


def test_frustum_pairs_keep_radii_above_min_radius_like_the_frustum_groundtruth(scene):
    database, queries = scene.database, scene.queries
    frusta = [
        TruncatedFrusta.of_images(images, np.arange(len(images)), 0.1, PAIRS["far"]) for images in (queries, database)
    ]
    radii = pairwise_overlap_radii(*frusta)
    positive = np.sort(radii[radii > 0])
    threshold = float(positive[len(positive) // 2])  # the radius of one pair: kept by >=, not by >
    selected = overlapping_pairs(
        queries, database, selection(max_per_image=None, min_radius=threshold), exclude_self=False
    )
    np.testing.assert_array_equal(selected, np.argwhere(radii > threshold))
    groundtruth = frustum_groundtruth(database, queries, depth=50, near=0.1, far=PAIRS["far"], min_radius=threshold)
    np.testing.assert_array_equal(selected, np.argwhere(groundtruth.relevance.toarray()))
    # at most max_per_image per query, the largest radii (ties: lower database index first)
    best = overlapping_pairs(queries, database, selection(max_per_image=2), exclude_self=False)
    expected = sorted(
        (q, int(t)) for q, row in enumerate(radii) for t in np.argsort(-row, kind="stable")[:2] if row[t] > 0
    )
    assert [tuple(p) for p in best.tolist()] == expected
    with pytest.raises(ValueError, match="min_radius: must be >= 0"):
        selection(min_radius=-1.0)
    with pytest.raises(ValueError, match="max_per_image: must be >= 1"):
        selection(max_per_image=0)


def test_database_co_observations_train_by_the_share_of_points_of_the_global_map(scene, cache):
    world = Scene("tiny", scene.database, scene.database.subset(np.arange(0)))
    counts = database_co_observations(world, SFM, cache).toarray()
    observations = global_map(SfmInputs.prepare(world, SFM, cache), None, cache).observations  # the cached map
    points = [set(ids[ids >= 0].tolist()) for ids in observations]
    expected = np.array([[len(a & b) for b in points] for a in points])
    np.testing.assert_array_equal(counts, expected)
    assert (expected[~np.eye(len(points), dtype=bool)] >= 5).sum() > len(points)  # many pairs share points
    settings = TrainingRelevanceSettings(
        {"_target_": CO_OBSERVATION, "min_shared": 5, "query_pairs": 50}, UnrelatedNegatives(0.1, None, None)
    )
    context = DefinitionContext(far=25.0, sfm=SFM, cache_dir=cache, world=world)
    graded = training_pairs(world.database, settings, context).graded.toarray()
    share = np.where(expected >= 5, expected / np.diag(expected)[:, None], 0.0)
    np.fill_diagonal(share, 0.0)
    np.testing.assert_allclose(graded, share)
    with pytest.raises(ValueError, match="co-observation training relevance needs the world's known-pose map"):
        training_pairs(scene.database, settings, DefinitionContext(far=25.0))
    with pytest.raises(ValueError, match="the images graded are not the database of scene 'tiny'"):
        training_pairs(scene.database.subset(np.arange(5)), settings, context)
