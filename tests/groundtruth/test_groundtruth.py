import dataclasses
import logging
from typing import ClassVar

import helpers
import numpy as np
import pytest
from helpers import compose_config, evaluate_config
from omegaconf import OmegaConf
from scipy.optimize import linprog
from scipy.spatial.transform import Rotation

from locretrieval import chebyshev, geometry
from locretrieval.chebyshev import chebyshev_radius
from locretrieval.config import ConfigError, validated
from locretrieval.frusta import INITIAL_BASIS, TruncatedFrusta, may_overlap, overlap_radii
from locretrieval.groundtruth import (
    FrustumDefinition,
    GroundTruth,
    RelativePoseDefinition,
    base,
    compute,
    compute_groundtruths,
)
from locretrieval.groundtruth import frustum_groundtruth as build_frustum
from locretrieval.groundtruth import relative_pose_groundtruth as build_relative_pose
from locretrieval.retrieval import EMPTY
from locretrieval.scene import Camera, ImageSet, Scene

# Square symmetric camera: half field of view 45 degrees (tan = 50 / 50).
WIDE = Camera("PINHOLE", 100, 100, (50.0, 50.0, 50.0, 50.0))
# Same image, twice the focal length: half field of view atan(0.5).
NARROW = Camera("PINHOLE", 100, 100, (100.0, 100.0, 50.0, 50.0))
NEAR = 0.1
FRUSTUM = {"_target_": "locretrieval.groundtruth.FrustumDefinition", "near": NEAR, "min_radius": 0.0}


def relative_pose_groundtruth(
    database, queries, depth=50, position_threshold=25.0, rotation_threshold=45.0, ranked="all"
):
    """The relative-pose ground truth with the paper's thresholds unless given, every image ranked."""
    return build_relative_pose(
        database,
        queries,
        depth=depth,
        position_threshold=position_threshold,
        rotation_threshold=rotation_threshold,
        ranked=ranked,
    )


def frustum_groundtruth(database, queries, depth=50, near=NEAR, far=25.0, min_radius=0.0):
    return build_frustum(database, queries, depth=depth, near=near, far=far, min_radius=min_radius)


def about(axis: str, degrees: float) -> np.ndarray:
    """wxyz quaternion of a rotation by ``degrees`` about a coordinate axis."""
    x, y, z, w = Rotation.from_euler(axis, degrees, degrees=True).as_quat()
    return np.array([w, x, y, z])


def image_set(qvec, centers, cameras=None, prefix="img") -> ImageSet:
    """Images with world-to-camera rotations ``qvec`` at world ``centers`` (NaN: no pose)."""
    qvec = np.asarray(qvec, dtype=float).reshape(-1, 4)
    centers = np.asarray(centers, dtype=float).reshape(-1, 3)
    n = len(qvec)
    tvec = geometry.translations_from_centers(qvec, centers)
    return ImageSet([f"{prefix}/{i}.jpg" for i in range(n)], "/nonexistent", cameras or [WIDE] * n, qvec, tvec)


def inscribed_radius_symmetric(tan_half_fov: float, far: float) -> float:
    """Closed form for a square symmetric pyramid truncated at ``far`` (near plane inactive).

    A ball on the axis at depth z touches the side planes at radius z sin(a) and the far
    plane at far - z; both are equal at the optimum: r = far sin(a) / (1 + sin(a)).
    """
    sine = np.sin(np.arctan(tan_half_fov))
    return far * sine / (1.0 + sine)


def linprog_radius(A: np.ndarray, b: np.ndarray) -> float:
    """Signed Chebyshev radius of ``A x <= b`` by scipy's HiGHS (rows of A unit-norm)."""
    G = np.hstack([A, np.linalg.norm(A, axis=1, keepdims=True)])
    solution = linprog([0.0, 0.0, 0.0, -1.0], A_ub=G, b_ub=b, bounds=[(None, None)] * 4, method="highs")
    assert solution.status == 0
    return -solution.fun


def random_cameras(rng: np.random.Generator, count: int, spread: float) -> ImageSet:
    """Random orientations, centres in a cube of side ``spread`` and varied intrinsics."""
    x, y, z, w = Rotation.random(count, random_state=rng.integers(1 << 31)).as_quat().T
    cameras = [
        Camera(
            "PINHOLE", 640, 480, (f, f * rng.uniform(0.9, 1.1), 320 + rng.uniform(-40, 40), 240 + rng.uniform(-30, 30))
        )
        for f in rng.uniform(250.0, 900.0, count)
    ]
    return image_set(np.stack([w, x, y, z], 1), rng.uniform(0, spread, (count, 3)), cameras)


def frusta(images: ImageSet, far: float) -> TruncatedFrusta:
    return TruncatedFrusta.of_images(images, np.arange(len(images)), NEAR, far)


def reference_radii(first: TruncatedFrusta, second: TruncatedFrusta) -> np.ndarray:
    """Signed linprog optimum of each pair's 12 half-spaces."""
    return np.array(
        [
            linprog_radius(np.concatenate([first.A[i], second.A[i]]), np.concatenate([first.b[i], second.b[i]]))
            for i in range(len(first))
        ]
    )


# ---------------------------------------------------------------- relative camera pose


@pytest.fixture
def pose_scene():
    """A query at the origin (identity rotation) and five database images with known errors.

    (c_diff m, R_diff deg) -> s = c/25 + R/45: d0 (10, 0) 0.4; d1 (0, 30) 0.667;
    d2 (20, 60) 2.133; d3 (30, 0) 1.2; d4 (5, 20) 0.644. Relevant: d0, d1, d4.
    """
    database = image_set(
        [about("x", 0), about("y", 30), about("z", 60), about("x", 0), about("x", 20)],
        [[10, 0, 0], [0, 0, 0], [20, 0, 0], [0, 30, 0], [3, 4, 0]],
        prefix="db",
    )
    queries = image_set(
        [about("x", 0), [np.nan] * 4, about("z", 10)], [[0, 0, 0], [np.nan] * 3, [500, 0, 0]], prefix="q"
    )
    return database, queries


def test_relative_pose_scores_order_and_relevance(pose_scene):
    database, queries = pose_scene
    gt = relative_pose_groundtruth(database, queries, depth=50)
    expected_s = {0: 10 / 25, 4: 5 / 25 + 20 / 45, 1: 30 / 45, 3: 30 / 25, 2: 20 / 25 + 60 / 45}
    assert gt.ranking.name == "gt_relative_pose" and gt.ranking.kind == "groundtruth"
    assert gt.ranking.indices[0].tolist() == [0, 4, 1, 3, 2]
    np.testing.assert_allclose(gt.ranking.scores[0], [-expected_s[i] for i in (0, 4, 1, 3, 2)], rtol=1e-6)
    assert gt.relevance[0].indices.tolist() == [0, 1, 4]
    # The query without a pose: no ranking, no relevance. The far query: ranked, none relevant.
    assert (gt.ranking.indices[1] == EMPTY).all() and gt.relevance[1].nnz == 0
    assert gt.ranking.lengths[2] == 5 and gt.relevance[2].nnz == 0
    assert gt.relevance.dtype == bool and gt.relevance.shape == (3, 5)


def test_relative_pose_ranks_only_images_within_the_thresholds_by_default(pose_scene):
    database, queries = pose_scene
    default = OmegaConf.load("configs/groundtruth/definitions/relative_pose.yaml").ranked
    gt = build_relative_pose(
        database, queries, depth=50, position_threshold=25.0, rotation_threshold=45.0, ranked=default
    )
    # the reference pairing: query 0 ranks its 3 relevant images by s (d0 0.4, d4 0.644, d1 0.667)
    assert gt.ranking.indices[0].tolist() == [0, 4, 1] + [EMPTY] * 2
    assert gt.ranking.lengths.tolist() == [3, 0, 0]  # the far query: nothing within 25 m and 45 deg
    assert (gt.relevance != relative_pose_groundtruth(database, queries).relevance).nnz == 0  # relevance unchanged
    with pytest.raises(ValueError, match="ranked: must be one of"):
        build_relative_pose(
            database, queries, depth=50, position_threshold=25.0, rotation_threshold=45.0, ranked="some"
        )


def test_relative_pose_thresholds_and_depth(pose_scene):
    database, queries = pose_scene
    gt = relative_pose_groundtruth(database, queries, depth=2, position_threshold=12.0, rotation_threshold=25.0)
    # s = c/12 + R/25: d0 0.833, d4 1.217, d1 1.2, d3 2.5, d2 4.07; relevant: c < 12 and R < 25.
    assert gt.ranking.indices[0].tolist() == [0, 1]
    assert gt.relevance[0].indices.tolist() == [0, 4]


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


def test_relative_pose_ignores_quaternion_signs(pose_scene):
    database, queries = pose_scene
    flipped_database = image_set(database.qvec, database.centers, prefix="db")
    flipped_queries = image_set(queries.qvec, queries.centers, prefix="q")
    flipped_database.qvec[:] = -database.qvec  # ImageSet normalises to w >= 0: force the sign back
    flipped_queries.qvec[:] = -queries.qvec
    a = relative_pose_groundtruth(database, queries)
    b = relative_pose_groundtruth(flipped_database, flipped_queries)
    np.testing.assert_array_equal(a.ranking.indices, b.ranking.indices)
    np.testing.assert_allclose(a.ranking.scores, b.ranking.scores, atol=1e-6)
    assert (a.relevance != b.relevance).nnz == 0


def test_statistics_count_all_relevant_images_over_posed_queries(pose_scene):
    database, queries = pose_scene
    statistics = relative_pose_groundtruth(database, queries, depth=2).statistics()
    # Query 0: 3 relevant, 2 of them in its top 2 (d0, d4); query 2: none; query 1: no pose.
    assert statistics == {
        "queries": 3,
        "queries_without_pose": 1,
        "depth": 2,
        "avg_relevant": 1.5,
        "avg_relevant_in_ranking": 1.0,
        "missing_pct": 50.0,
    }


def test_statistics_without_any_posed_query(pose_scene):
    database, queries = pose_scene
    statistics = relative_pose_groundtruth(database, queries.subset([1])).statistics()
    assert statistics["queries_without_pose"] == 1 and np.isnan(statistics["avg_relevant"])


def test_groundtruth_rejects_rankings_for_queries_without_pose(pose_scene):
    database, queries = pose_scene
    gt = relative_pose_groundtruth(database, queries)
    with pytest.raises(ValueError, match="without a pose"):
        GroundTruth(gt.ranking, gt.relevance, np.array([True, True, False]))


# ---------------------------------------------------------------- frustum overlap


def test_identical_frusta_give_the_inscribed_radius_of_one():
    images = image_set([about("y", 0), about("y", 0)], [[0, 0, 0], [0, 0, 0]], [WIDE, NARROW])
    radii = overlap_radii(frusta(images, 10.0), frusta(images, 10.0))
    np.testing.assert_allclose(
        radii, [inscribed_radius_symmetric(1.0, 10.0), inscribed_radius_symmetric(0.5, 10.0)], rtol=1e-9
    )
    # A non-square, off-centre camera against scipy linprog on its own 6 half-spaces.
    odd = image_set(about("x", 30), [1, 2, 3], [Camera("PINHOLE", 640, 360, (400.0, 420.0, 300.0, 200.0))])
    single = frusta(odd, 10.0)
    assert overlap_radii(single, single)[0] == pytest.approx(linprog_radius(single.A[0], single.b[0]), rel=1e-9)


def test_contained_frustum_gives_the_radius_of_the_smaller_one():
    wide = image_set(about("y", 0), [0, 0, 0], [WIDE])
    narrow = image_set(about("y", 0), [0, 0, 0], [NARROW])
    shorter = overlap_radii(frusta(wide, 10.0), frusta(wide, 4.0))[0]
    assert shorter == pytest.approx(inscribed_radius_symmetric(1.0, 4.0), rel=1e-9)
    narrower = overlap_radii(frusta(wide, 10.0), frusta(narrow, 10.0))[0]
    assert narrower == pytest.approx(inscribed_radius_symmetric(0.5, 10.0), rel=1e-9)


def test_disjoint_and_touching_frusta_have_zero_radius():
    # Back to back at one centre (the near planes keep them apart), 100 m apart, and
    # facing each other with far planes meeting in the plane z = 10 (touching only).
    first = image_set([about("y", 0)] * 3, [[0, 0, 0]] * 3)
    second = image_set([about("y", 180), about("y", 0), about("y", 180)], [[0, 0, 0], [100, 0, 0], [0, 0, 20]])
    radii = overlap_radii(frusta(first, 10.0), frusta(second, 10.0))
    assert radii[:2].tolist() == [0.0, 0.0]
    assert radii[2] == 0.0
    assert not may_overlap(frusta(first, 10.0)[:2], frusta(second, 10.0)[:2]).any()


@pytest.fixture(scope="module")
def random_pairs():
    """300 random frustum pairs (far 20 m, centres within 15 m) and their linprog radii."""
    rng = np.random.default_rng(0)
    first, second = frusta(random_cameras(rng, 300, 15.0), 20.0), frusta(random_cameras(rng, 300, 15.0), 20.0)
    return first, second, reference_radii(first, second)


def signed_radii(first: TruncatedFrusta, second: TruncatedFrusta) -> np.ndarray:
    A = np.concatenate([first.A, second.A], axis=1)
    b = np.concatenate([first.b, second.b], axis=1)
    return chebyshev_radius(A, b, INITIAL_BASIS)  # every pair, empty intersections included


def test_batched_solver_equals_linprog_on_random_pairs(random_pairs):
    first, second, expected = random_pairs
    assert 0.2 < (expected > 0).mean() < 0.8  # both overlapping and empty pairs are exercised
    np.testing.assert_allclose(signed_radii(first, second), expected, rtol=1e-6, atol=1e-6 * 20.0)
    np.testing.assert_allclose(overlap_radii(first, second), np.maximum(expected, 0.0), rtol=1e-6, atol=1e-6 * 20.0)


@pytest.mark.parametrize("constant, value", [("DANTZIG_PIVOTS", 0), ("MAX_PIVOTS", 2)])
def test_bland_rule_and_linprog_fallback_agree_with_linprog(random_pairs, monkeypatch, caplog, constant, value):
    first, second, expected = random_pairs
    monkeypatch.setattr(chebyshev, constant, value)
    with caplog.at_level(logging.INFO, logger=chebyshev.__name__):
        radii = signed_radii(first, second)
    np.testing.assert_allclose(radii, expected, rtol=1e-6, atol=1e-6 * 20.0)
    assert ("re-solved with scipy linprog" in caplog.text) == (constant == "MAX_PIVOTS")


def test_prefilter_keeps_every_pair_that_linprog_says_overlaps():
    rng = np.random.default_rng(1)
    first, second = frusta(random_cameras(rng, 400, 40.0), 15.0), frusta(random_cameras(rng, 400, 40.0), 15.0)
    kept = may_overlap(first, second)
    expected = reference_radii(first, second)
    assert (~kept).sum() > 100  # the prefilter does discard pairs
    assert (expected[~kept] <= 1e-9).all()
    assert (expected > 1e-9).sum() > 20


def test_frustum_groundtruth_ranks_by_radius_and_skips_empty_pairs():
    rng = np.random.default_rng(2)
    database = random_cameras(rng, 40, 25.0)
    queries = random_cameras(rng, 6, 25.0)
    queries.qvec[4] = np.nan  # a query without a pose
    gt = frustum_groundtruth(database, queries, depth=10, far=15.0, min_radius=0.5)
    posed = np.flatnonzero(queries.has_pose)
    query_frusta = TruncatedFrusta.of_images(queries, posed, NEAR, 15.0)
    database_frusta = frusta(database, 15.0)
    for row, q in enumerate(posed):
        pairs = np.full(len(database), row)
        expected = np.maximum(reference_radii(query_frusta[pairs], database_frusta), 0.0)
        order = np.argsort(-expected, kind="stable")
        order = order[expected[order] > 1e-9][:10]
        assert gt.ranking.indices[q, : len(order)].tolist() == order.tolist()
        assert (gt.ranking.indices[q, len(order) :] == EMPTY).all()
        np.testing.assert_allclose(gt.ranking.scores[q, : len(order)], expected[order], rtol=1e-5)
        assert gt.relevance[q].indices.tolist() == np.flatnonzero(expected > 0.5).tolist()
    assert (gt.ranking.indices[4] == EMPTY).all() and gt.relevance[4].nnz == 0
    assert gt.relevance.nnz > 0 and (gt.ranking.lengths[posed] < 10).any()


def test_bad_planes_and_unposed_database_images_are_rejected(pose_scene):
    database, queries = pose_scene
    with pytest.raises(ValueError, match=r"far: must exceed near \(5.0 m\), got 2.0"):
        frustum_groundtruth(database, queries, near=5.0, far=2.0)
    database.tvec[3] = np.nan
    with pytest.raises(ValueError, match=r"database images without a pose: \['db/3.jpg'\]"):
        relative_pose_groundtruth(database, queries)


# ---------------------------------------------------------------- configuration and cache


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


def test_chunked_scoring_equals_one_chunk(pose_scene, monkeypatch):
    database, queries = pose_scene
    whole = frustum_groundtruth(database, queries, far=30.0)
    monkeypatch.setattr(base, "PAIRS_PER_CHUNK", 1)  # one query per chunk
    chunked = frustum_groundtruth(database, queries, far=30.0)
    np.testing.assert_array_equal(chunked.ranking.indices, whole.ranking.indices)
    np.testing.assert_array_equal(chunked.ranking.scores, whole.ranking.scores)
    assert (chunked.relevance != whole.relevance).nnz == 0


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
