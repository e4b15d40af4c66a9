"""The SfM pipeline's verbs (`locretrieval.sfm.pipeline`) as paradigms 2a (local SfM) and 2b (global SfM) run them,
and its building blocks, on a tiny rendered scene."""

import dataclasses
import shutil

import helpers
import kapture.io.records as kapture_records
import numpy as np
import pycolmap
import pytest
from PIL import Image

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval import geometry
from locretrieval.config import validated
from locretrieval.frusta import TruncatedFrusta, pairwise_overlap_radii
from locretrieval.groundtruth import relative_pose_groundtruth
from locretrieval.paradigms import global_sfm, local_sfm
from locretrieval.paradigms.base import Paradigms
from locretrieval.paradigms.global_sfm import GlobalSfm, global_map, map_cache_path
from locretrieval.paradigms.local_sfm import LocalSfm, local_map_pairs
from locretrieval.paradigms.sfm import run_sfm
from locretrieval.retrieval import Ranking, random_ranking
from locretrieval.scene.kapture_io import load_kapture_scene
from locretrieval.scene.synthetic import render_synthetic_dataset
from locretrieval.sfm import matching, pipeline
from locretrieval.sfm import triangulation as triangulation_module
from locretrieval.sfm.colmap_model import read_colmap_map, to_pycolmap_camera, to_rigid3d
from locretrieval.sfm.features import FeatureStore, extract_features
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.pairs import PairSelection, database_pairs
from locretrieval.sfm.pnp import (
    NO_3D_POINTS,
    NO_KEYPOINTS,
    TOO_FEW_IMAGES,
    TOO_FEW_MATCHES,
    estimate_absolute_pose,
)
from locretrieval.sfm.settings import SfmSettings
from locretrieval.sfm.work import Work

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
    "seed": 1,
}


BLANK = 7  # this query's image is replaced by a uniform one


PAIRS = {"far": 25.0, "max_per_image": 10}  # global-map pairs (the scene has no frustum_far)


def sfm_settings(triangulation_kind: str = "colmap", **overrides) -> SfmSettings:
    """The default SfM settings in this process (``sfm/triangulation=<triangulation_kind>``),
    global-map pairs by `PAIRS`, ``overrides`` merged in."""
    return helpers.sfm_settings({"map_pairs": PAIRS}, overrides, choices=[f"sfm/triangulation={triangulation_kind}"])


MAP_MATCHES = {"database": local_sfm.DatabaseMapMatches(), "query": local_sfm.QueryMapMatches()}


def run_local(scene, rankings, k, cache, map_matches="database", sfm=None):
    """Paradigm 2a with the given ks, its map matches by name (`MAP_MATCHES`)."""
    return LocalSfm(True, list(k), MAP_MATCHES[map_matches]).run(scene, rankings, sfm or sfm_settings(), cache)


def run_global(scene, rankings, k, cache, colmap_model=None, sfm=None):
    """Paradigm 2b with the given ks."""
    return GlobalSfm(True, list(k), colmap_model).run(scene, rankings, sfm or sfm_settings(), cache)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("sfm_scene")
    render_synthetic_dataset(helpers.render_settings(SCENE), root)
    blank = root / "query" / "sensors" / "records_data" / "query" / f"{BLANK:06d}.png"
    Image.new("RGB", (SCENE["width"], SCENE["height"]), (128, 128, 128)).save(blank)
    return load_kapture_scene("tiny", [root / "mapping"], [root / "query"])


@pytest.fixture(scope="module")
def features_cache(scene, tmp_path_factory):
    """A cache folder holding the features of both image sets (copied into fresh caches)."""
    cache = tmp_path_factory.mktemp("sfm_features")
    extract_features(scene.database, sfm_settings().features, cache, workers=1)
    extract_features(scene.queries, sfm_settings().features, cache, workers=1)
    return cache


@pytest.fixture
def cache(features_cache, tmp_path):
    shutil.copytree(features_cache / "features", tmp_path / "features")
    return tmp_path


@pytest.fixture(scope="module")
def rankings(scene):
    database, queries = scene.database, scene.queries
    truth = relative_pose_groundtruth(
        database, queries, depth=50, position_threshold=25.0, rotation_threshold=45.0, ranked="within_thresholds"
    )
    return [truth.ranking, random_ranking(len(queries), len(database), 50, 0)]


def read_depth(images, index):
    camera = images.cameras[index]
    return kapture_records.depth_map_from_file(str(images.depth_paths[index]), (camera.width, camera.height))


def backproject(images, index, pixels):
    """World points seen at ``pixels`` (COLMAP convention) of image ``index``, by its rendered depth."""
    depth = read_depth(images, index)
    z = depth[pixels[:, 1].astype(int), pixels[:, 0].astype(int)]
    rays = np.column_stack([pixels, np.ones(len(pixels))]) @ np.linalg.inv(images.cameras[index].calibration_matrix()).T
    return (rays * z[:, None] - images.tvec[index]) @ geometry.quaternion_to_matrix(images.qvec[index])


@pytest.mark.parametrize("kind", ["colmap", "batched"])
def test_triangulation_with_known_poses_recovers_the_rendered_points(scene, cache, monkeypatch, kind):
    database = scene.database
    inputs = SfmInputs.prepare(scene, sfm_settings(kind), cache)
    sparse_map = global_map(inputs, None, cache)
    assert sparse_map.num_points > 500
    keypoints = inputs.database_features.keypoints(database.names)
    track_lengths = np.bincount(
        np.concatenate([ids[ids >= 0] for ids in sparse_map.observations]), minlength=sparse_map.num_points
    )
    errors, lengths = [], []
    for index, name in enumerate(database.names):
        observed = np.flatnonzero(sparse_map.observations[index] >= 0)
        points = sparse_map.observations[index][observed]
        truth = backproject(database, index, keypoints[name][observed])
        errors.append(np.linalg.norm(truth - sparse_map.points[points], axis=1))
        lengths.append(track_lengths[points])
    errors, lengths = np.concatenate(errors), np.concatenate(lengths)
    assert np.median(errors) < 0.03
    # tracks over three or more images are right to centimetres; the tail: keypoints on depth
    # edges (they read the background's depth) and two-view tracks of repeated textures
    assert np.median(errors[lengths >= 3]) < 0.015 and np.mean(errors[lengths >= 3] < 0.1) > 0.8
    # cached: the same map is read back, without reading any feature
    monkeypatch.setattr(FeatureStore, "keypoints", None)
    monkeypatch.setattr(FeatureStore, "load", None)
    again = global_map(inputs, None, cache)
    np.testing.assert_array_equal(again.points, sparse_map.points)


def test_the_global_map_cache_key_follows_what_the_map_depends_on(scene, cache):
    def path(**overrides):
        inputs = SfmInputs.prepare(scene, sfm_settings(**overrides), cache)
        return map_cache_path(inputs, cache)

    base = path()
    assert (
        path(
            query_verification={
                "_target_": "locretrieval.sfm.verification.TwoViewVerification",
                "max_error": 3.0,
                "min_num_inliers": 15,
            }
        )
        == base
    )  # query pairs only
    assert path(triangulation={"min_angle": 3.0}) != base
    assert path(matching={"ratio": 0.9}) != base
    assert path(database_verification={"max_epipolar_error": 8.0}) != base
    assert path(map_pairs={"far": 30.0}) != base
    assert path(pnp={"max_error": 6.0}) == base  # registration only


def test_feature_keypoints_are_read_without_descriptors(scene, cache):
    inputs = SfmInputs.prepare(scene, sfm_settings(), cache)
    keypoints = inputs.database_features.keypoints(scene.database.names[:3])
    assert all(points.shape[1] == 2 for points in keypoints.values())
    assert {name for _, name in inputs.database_features.store._cache} == {"keypoints"}


def test_pnp_recovers_a_rendered_query_pose_among_outliers(scene):
    queries = scene.queries
    rng = np.random.default_rng(0)
    depth = read_depth(queries, 0)
    rows, columns = np.nonzero(depth > 0)
    chosen = rng.choice(len(rows), 300, replace=False)
    pixels = np.column_stack([columns[chosen], rows[chosen]]) + 0.5  # pixel centres, COLMAP convention
    points = backproject(queries, 0, pixels)
    points[:90] = rng.uniform(points.min(0), points.max(0), (90, 3))  # 30 % outliers
    pnp = sfm_settings().pnp
    qvec, tvec, inliers = estimate_absolute_pose(pixels, points, queries.cameras[0], pnp)
    assert 205 <= inliers <= 215
    assert geometry.position_errors(geometry.camera_centers(qvec, tvec), queries.centers[0]) < 1e-3
    assert geometry.rotation_errors_deg(qvec, queries.qvec[0]) < 0.01
    assert estimate_absolute_pose(pixels[:5], points[:5], queries.cameras[0], pnp) == TOO_FEW_MATCHES


def test_paradigms_localise_with_the_ground_truth_ranking_and_count_failures(scene, cache, rankings):
    queries = scene.queries
    posed = np.arange(len(queries)) != BLANK
    local = run_local(scene, rankings, [1, 3, 5], cache)
    globl = run_global(scene, rankings, [1, 3], cache)
    by_name = {(e.paradigm, e.ranking): e for e in local + globl}
    assert sorted(by_name) == sorted(
        (p, r) for p in ("local_sfm", "global_sfm") for r in ("gt_relative_pose", "random")
    )
    for estimates in by_name.values():
        assert estimates.method == "pnp"
        # the blank image has no keypoint, whatever k; k=1 cannot build a local map
        assert (estimates.failures[:, BLANK] == NO_KEYPOINTS).all() or (
            estimates.paradigm == "local_sfm" and estimates.failures[0, BLANK] == TOO_FEW_IMAGES
        )
        if estimates.paradigm == "local_sfm":
            assert (estimates.failures[0] == TOO_FEW_IMAGES).all()
    localized = {}
    for key, estimates in by_name.items():
        position, rotation = estimates.errors(queries.qvec, queries.tvec)
        localized[key] = ((position < 0.25) & (rotation < 2.0))[:, posed].mean(axis=1)
    assert localized[("local_sfm", "gt_relative_pose")][2] >= 0.7  # k = 5
    assert localized[("global_sfm", "gt_relative_pose")][1] >= 0.7  # k = 3
    for paradigm in ("local_sfm", "global_sfm"):
        assert (localized[(paradigm, "random")] <= localized[(paradigm, "gt_relative_pose")]).all()
    position, _ = by_name[("global_sfm", "gt_relative_pose")].errors(queries.qvec, queries.tvec)
    assert np.nanmedian(position[1]) < 0.05


def test_local_maps_from_query_derived_matches_match_no_database_pair(scene, cache, rankings, monkeypatch):
    calls = count_matcher_calls(monkeypatch)
    estimates = run_local(scene, rankings[:1], [5], cache, map_matches="query")[0]
    assert sum(calls) == len(scene.queries) * 5  # query pairs only
    position, rotation = estimates.errors(scene.queries.qvec, scene.queries.tvec)
    assert ((position < 0.25) & (rotation < 2.0)).mean() >= 0.6


class NoMapMatches(local_sfm.MapMatches):
    """Map matches from outside the package: none at all, so no local map has a point."""

    def identity(self):
        return f"{__name__}.NoMapMatches"

    def source(self, inputs, query):
        return []

    def matches(self, pairs, query):
        return {pair: np.empty((0, 2), dtype=np.int32) for pair in pairs}


def test_map_matches_from_outside_the_package_are_chosen_through_the_config(scene, cache, rankings, monkeypatch):
    cfg = helpers.evaluate_config(
        "paths.root_dir=/nonexistent",
        f"paradigms.local_sfm.map_matches._target_={__name__}.NoMapMatches",
        "paradigms.local_sfm.k=[1,5]",
    )
    settings = validated(Paradigms, cfg.paradigms, "paradigms").local_sfm
    assert isinstance(settings.map_matches, NoMapMatches)
    calls = count_matcher_calls(monkeypatch)
    estimates = settings.run(scene, rankings[:1], sfm_settings(), cache)[0]
    assert sum(calls) == len(scene.queries) * 5  # query pairs only: no database pair is matched
    assert (estimates.failures[0] == TOO_FEW_IMAGES).all() and (estimates.failures[1] == NO_3D_POINTS).all()
    for choice, kind in (
        ([], local_sfm.DatabaseMapMatches),
        (["paradigms/local_sfm/map_matches=query"], local_sfm.QueryMapMatches),
    ):
        paradigms = helpers.evaluate_config("paths.root_dir=/nonexistent", *choice).paradigms
        assert type(validated(Paradigms, paradigms, "paradigms").local_sfm.map_matches) is kind


def count_matcher_calls(monkeypatch) -> list[int]:
    """Spy on the matcher (workers=1 runs it in this process): pairs matched per call."""
    calls = []
    real = matching.NearestNeighbourMatcher.__call__

    def counting(self, first, others):
        calls.append(len(others))
        return real(self, first, others)

    monkeypatch.setattr(matching.NearestNeighbourMatcher, "__call__", counting)
    return calls


def test_increasing_k_matches_only_the_new_pairs(scene, cache, rankings, monkeypatch):
    calls = count_matcher_calls(monkeypatch)

    def pairs(k):
        """Query pairs and database pairs of local maps up to k, by explicit enumeration."""
        query, database = set(), set()
        for ranking in rankings:
            for q, row in enumerate(ranking.indices[:, :k]):
                query.update((q, int(i)) for i in row)
                database.update((min(a, b), max(a, b)) for a in row for b in row if a != b)
        return query, database

    run_local(scene, rankings, [3], cache)
    query3, database3 = pairs(3)
    assert sum(calls) == len(query3) + len(database3)
    assert {tuple(p) for p in local_map_pairs(rankings, [[3], [3]]).tolist()} == database3
    calls.clear()
    run_local(scene, rankings, [3, 5], cache)
    query5, database5 = pairs(5)
    assert sum(calls) == len(query5 - query3) + len(database5 - database3)
    calls.clear()
    run_local(scene, rankings, [2, 5], cache)
    assert sum(calls) == 0


def test_local_maps_of_the_same_images_in_another_order_are_built_once(scene, cache, rankings, monkeypatch):
    truth = rankings[0]
    top = truth.indices[:, :3]
    reversed_ranking = Ranking("reversed", top[:, ::-1], truth.scores[:, :3][:, ::-1], "groundtruth")
    built = []
    real = triangulation_module.triangulate_known_poses

    def counting(cameras, qvec, tvec, *rest):
        built.append(len(cameras))
        return real(cameras, qvec, tvec, *rest)

    monkeypatch.setattr(triangulation_module, "triangulate_known_poses", counting)
    forward, backward = run_local(scene, [truth.top(3), reversed_ranking], [2, 3], cache)
    # per query: the two top-2 sets {first, second} and {second, third}, and one top-3 set; a
    # set that several queries share is triangulated once (then read from the cache)
    sets = {frozenset(row[:2]) for row in top} | {frozenset(row[1:]) for row in top} | {frozenset(row) for row in top}
    assert sorted(built) == sorted(len(images) for images in sets)
    np.testing.assert_array_equal(forward.qvec[1], backward.qvec[1])
    np.testing.assert_array_equal(forward.tvec[1], backward.tvec[1])
    np.testing.assert_array_equal(forward.failures[1], backward.failures[1])


@pytest.mark.parametrize("map_matches", ["database", "query"])
def test_a_rerun_reads_its_local_maps_from_the_cache(scene, cache, rankings, monkeypatch, map_matches):
    first = run_local(scene, rankings, [2, 3], cache, map_matches)
    assert len(list((cache / "local_maps").glob("*.npz"))) > 0

    def refuse(*_):
        raise AssertionError("a cached local map was triangulated again")

    monkeypatch.setattr(triangulation_module, "triangulate_known_poses", refuse)
    shutil.rmtree(cache / "poses")  # registered again, in maps read from the cache
    again = run_local(scene, rankings, [2, 3], cache, map_matches)
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.qvec, b.qvec)
        np.testing.assert_array_equal(a.failures, b.failures)
    other = sfm_settings(triangulation={"min_angle": 3.0})  # another map: built, not read
    monkeypatch.undo()
    before = len(list((cache / "local_maps").glob("*.npz")))
    run_local(scene, rankings, [2], cache, map_matches, sfm=other)
    assert len(list((cache / "local_maps").glob("*.npz"))) > before


@pytest.mark.parametrize("paradigm", ["local_sfm", "global_sfm"])
def test_registrations_are_cached_by_query_and_image_set(scene, cache, rankings, monkeypatch, paradigm):
    run, module = (run_local, local_sfm) if paradigm == "local_sfm" else (run_global, global_sfm)
    truth, other = rankings
    first = run(scene, [truth], [2, 3], cache)[0]
    registered = []
    real = module.register_query

    def recording(inputs, query, keypoints, matches, *rest):
        registered.append((query, tuple(sorted(matches))))
        return real(inputs, query, keypoints, matches, *rest)

    monkeypatch.setattr(module, "register_query", recording)
    again, added = run(scene, [truth, other], [2, 3], cache)
    for name in ("qvec", "tvec", "failures"):
        np.testing.assert_array_equal(getattr(first, name), getattr(again, name))
    # only the new ranking's image sets are registered, each once
    truth_sets = {(q, tuple(sorted(row[:k]))) for q, row in enumerate(truth.indices) for k in (2, 3)}
    assert registered and not set(registered) & truth_sets
    assert len(registered) == len(set(registered))
    fresh = cache.parent / f"{cache.name}-fresh"
    shutil.copytree(cache / "features", fresh / "features")
    alone = run(scene, [other], [2, 3], fresh)[0]
    np.testing.assert_array_equal(added.failures, alone.failures)
    np.testing.assert_allclose(added.tvec, alone.tvec, atol=1e-9)
    registered.clear()
    run(scene, [truth], [2, 3], cache, sfm=sfm_settings(pnp={"max_error": 6.0}))  # other PnP settings: not read
    assert registered


def test_results_do_not_depend_on_worker_processes_and_reruns_reuse_the_caches(scene, cache, rankings, monkeypatch):
    parallel = run_global(scene, rankings, [1, 3], cache, sfm=sfm_settings(workers=2))
    calls = count_matcher_calls(monkeypatch)
    shutil.rmtree(cache / "poses")  # registered again, in this process
    serial = run_global(scene, rankings, [1, 3], cache)
    assert sum(calls) == 0  # features, matches and the map all come from the cache
    for a, b in zip(parallel, serial):
        np.testing.assert_array_equal(a.qvec, b.qvec)
        np.testing.assert_array_equal(a.tvec, b.tvec)
        np.testing.assert_array_equal(a.failures, b.failures)


@dataclasses.dataclass
class RecordedChunks(LocalSfm):
    """Local SfM recording the queries of each call of its per-query stage."""

    chunks: list = dataclasses.field(default_factory=list)

    def register(self, inputs, rankings, ks, queries):
        self.chunks.append(queries)
        return super().register(inputs, rankings, ks, queries)


def test_queries_streamed_in_chunks_give_the_results_of_one_pass(scene, cache, rankings, monkeypatch, tmp_path):
    """Chunks of 3 of the 8 queries: each chunk's pairs matched while the last chunk is triangulated
    and registered (a thread and 2 workers), then the outcomes gathered: those of one pass."""
    paradigms = {
        "local_sfm": RecordedChunks(True, [2, 4], MAP_MATCHES["database"]),
        "global_sfm": GlobalSfm(True, [1, 3], None),
    }
    one_pass = run_sfm(SfmInputs.prepare(scene, sfm_settings(), cache, extract=False), rankings, paradigms).estimates
    shutil.copytree(cache / "features", tmp_path / "streamed" / "features")
    monkeypatch.setattr(pipeline, "QUERIES_PER_CHUNK", 3)
    chunks = paradigms["local_sfm"].chunks
    chunks.clear()
    inputs = SfmInputs.prepare(scene, sfm_settings(workers=2), tmp_path / "streamed", extract=False)
    run = run_sfm(inputs, rankings, paradigms)
    streamed = run.estimates
    assert chunks == [[0, 1, 2], [3, 4, 5], [6, 7], None]  # three chunks, then every outcome gathered from the cache
    assert set(run.stages) == {
        "features",
        "match + verify",
        "local_sfm: triangulate",  # each chunk's local maps, in the workers
        "local_sfm: register",
        "global_sfm: triangulate",  # the global map, once
        "global_sfm: register",
    }
    planned = {stage: units for stage, (units, _) in run.plan.stage_units().items()}
    assert planned["match + verify"] and planned["local_sfm: register"] and planned["global_sfm: triangulate"] == 1
    assert {stage: record.done for stage, record in run.stages.items()} == planned  # each stage's progress, counted
    for name in paradigms:
        for a, b in zip(one_pass[name], streamed[name]):
            np.testing.assert_array_equal(a.qvec, b.qvec)
            np.testing.assert_array_equal(a.tvec, b.tvec)
            np.testing.assert_array_equal(a.failures, b.failures)
        assert any((e.failures == "").any() for e in streamed[name])


def write_colmap_model(folder, database, keypoints, sparse_map):
    """The map as a COLMAP model whose images have the feature keypoints as 2D points."""
    model = pycolmap.Reconstruction()
    for index, name in enumerate(database.names):
        model.add_camera_with_trivial_rig(to_pycolmap_camera(database.cameras[index], index + 1))
        image = pycolmap.Image(
            name=name, keypoints=keypoints[name].astype(np.float64), camera_id=index + 1, image_id=index + 1
        )
        model.add_image_with_trivial_frame(image, to_rigid3d(database.qvec[index], database.tvec[index]))
    for row, xyz in enumerate(sparse_map.points):
        track = pycolmap.Track()
        for index, ids in enumerate(sparse_map.observations):
            for keypoint in np.flatnonzero(ids == row):
                track.add_element(index + 1, int(keypoint))
        model.add_point3D(xyz, track)
    folder.mkdir()
    model.write_text(folder)


def test_an_existing_colmap_model_serves_as_the_global_map(scene, cache, rankings, tmp_path):
    database = scene.database
    inputs = SfmInputs.prepare(scene, sfm_settings(), cache)
    sparse_map = global_map(inputs, None, cache)
    keypoints = inputs.database_features.keypoints(database.names)
    write_colmap_model(tmp_path / "model", database, keypoints, sparse_map)
    read = read_colmap_map(tmp_path / "model", database.names, [keypoints[n] for n in database.names])
    assert read.num_points == sparse_map.num_points
    for ours, theirs in zip(sparse_map.observations, read.observations):
        observed = ours >= 0
        np.testing.assert_array_equal(observed, theirs >= 0)
        np.testing.assert_allclose(read.points[theirs[observed]], sparse_map.points[ours[observed]])
    from_model = run_global(scene, rankings[:1], [3], cache, colmap_model=str(tmp_path / "model"))
    triangulated = run_global(scene, rankings[:1], [3], cache)
    np.testing.assert_array_equal(from_model[0].failures, triangulated[0].failures)
    np.testing.assert_allclose(from_model[0].tvec, triangulated[0].tvec, atol=1e-6)
    shifted = [keypoints[n] + 1.0 for n in database.names]
    with pytest.raises(ValueError, match="2D points are not the .* feature keypoints"):
        read_colmap_map(tmp_path / "model", database.names, shifted)


@pytest.mark.parametrize("kind", ["colmap", "batched"])
def test_triangulating_pairs_without_matches_gives_an_empty_map(scene, kind):
    database = scene.database.subset(np.arange(3))
    keypoints = [np.zeros((4, 2)), np.zeros((0, 2)), np.ones((2, 2))]
    no_matches = {(0, 2): np.empty((0, 2), np.int32)}
    sparse_map = sfm_settings(kind).triangulation.triangulate(
        database.cameras, database.qvec, database.tvec, keypoints, no_matches
    )
    assert sparse_map.num_points == 0 and [len(o) for o in sparse_map.observations] == [4, 0, 2]


def test_global_map_pairs_are_the_most_overlapping_frusta(scene):
    database = scene.database
    pairs = database_pairs(database, PairSelection(near=0.1, far=25.0, min_radius=0.0, max_per_image=3))
    assert (pairs[:, 0] < pairs[:, 1]).all() and len(np.unique(pairs, axis=0)) == len(pairs)
    frusta = TruncatedFrusta.of_images(database, np.arange(len(database)), 0.1, 25.0)
    radii = pairwise_overlap_radii(frusta, frusta)
    np.fill_diagonal(radii, 0.0)
    chosen = {tuple(p) for p in pairs.tolist()}
    for image, row in enumerate(radii):
        best = [int(j) for j in np.argsort(-row, kind="stable")[:3] if row[j] > 0]
        assert all((min(image, j), max(image, j)) in chosen for j in best)
    # every chosen pair is among the best three of one of its images
    assert all(
        b in np.argsort(-radii[a], kind="stable")[:3] or a in np.argsort(-radii[b], kind="stable")[:3] for a, b in pairs
    )
    assert len(database_pairs(database, PairSelection(near=0.1, far=25.0, min_radius=1e6, max_per_image=None))) == 0


def distinct_work(rankings, ks):
    """Independently counted: query pairs of the top max(ks), database pairs within them, and
    the distinct (query, top-k set) registrations and top-k sets of two or more images."""
    query_pairs, database_pairs_, registrations, maps = set(), set(), set(), set()
    for ranking in rankings:
        for q, row in enumerate(ranking.indices):
            top = [int(i) for i in row[: max(ks)] if i >= 0]
            query_pairs.update((q, i) for i in top)
            database_pairs_.update((min(a, b), max(a, b)) for a in top for b in top if a != b)
            for k in ks:
                images = tuple(sorted(top[:k]))
                registrations.add((q, images))
                maps.update([images] if len(images) >= 2 else [])
    return query_pairs, database_pairs_, registrations, maps


def test_the_plan_counts_the_work_that_the_paradigms_then_do(scene, cache, rankings, monkeypatch):
    sfm = sfm_settings()
    local, global_ = LocalSfm(True, [3, 5], MAP_MATCHES["database"]), GlobalSfm(True, [1, 5], None)

    def plans():
        inputs = SfmInputs.prepare(scene, sfm, cache, extract=False)
        return local.count(inputs, rankings, 0), global_.count(inputs, rankings, 0)

    local_work, global_work = plans()
    query_pairs, pairs_within, local_registrations, maps = distinct_work(rankings, [3, 5])
    assert local_work.query_pairs == global_work.query_pairs == Work(len(query_pairs), len(query_pairs))
    assert local_work.database_pairs == Work(len(pairs_within), len(pairs_within))
    assert local_work.maps == Work(len(maps), len(maps)) and local_work.registrations == Work(
        len(local_registrations), len(local_registrations)
    )
    map_pairs = len(database_pairs(scene.database, sfm.map_pairs.for_scene(scene)))
    assert global_work.database_pairs == Work(map_pairs, map_pairs) and global_work.maps == Work(1, 1)
    global_registrations = len(distinct_work(rankings, [1, 5])[2])
    assert global_work.registrations == Work(global_registrations, global_registrations)
    # the runs match exactly the new pairs the plans counted
    calls = count_matcher_calls(monkeypatch)
    local.run(scene, rankings, sfm, cache)
    assert sum(calls) == len(query_pairs) + len(pairs_within)
    calls.clear()
    global_.run(scene, rankings, sfm, cache)
    already = len(
        {(min(a, b), max(a, b)) for a, b in database_pairs(scene.database, sfm.map_pairs.for_scene(scene))}
        & pairs_within
    )
    assert sum(calls) == map_pairs - already
    # afterwards nothing is new
    local_after, global_after = plans()
    assert (
        local_after.query_pairs.new
        == local_after.database_pairs.new
        == local_after.maps.new
        == local_after.registrations.new
        == 0
    )
    assert global_after.query_pairs.new == global_after.maps.new == global_after.registrations.new == 0
    assert (local_after.maps.total, global_after.registrations.total) == (len(maps), global_registrations)
