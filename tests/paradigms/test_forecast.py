"""The dry run's forecast (`locretrieval.paradigms.forecast`): the units of each stage times the unit costs
one calibration measured, spread over the processes the pipeline gives the stage; the paradigms'
counts less what the ground truth matches first; a calibration that leaves nothing behind."""

import dataclasses
from math import comb

import helpers
import numpy as np
import pytest

from locretrieval.benchmark import BenchmarkSettings
from locretrieval.build import benchmark_settings
from locretrieval.config import validated
from locretrieval.groundtruth.compute import GroundTruthSettings, groundtruth_sfm_pairs
from locretrieval.paradigms.forecast import (
    CALIBRATION_DATABASE,
    CALIBRATION_QUERIES,
    GROUNDTRUTH_MAP,
    GROUNDTRUTH_MATCHING,
    Calibration,
    after_groundtruth,
    calibrate,
    calibration_sample,
    counted_plan,
    dry_run_forecast,
    forecast,
)
from locretrieval.paradigms.sfm import count_work, run_sfm
from locretrieval.retrieval import Ranking, random_ranking
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.work import ParadigmWork, SfmPlan, Work

#: Rendered in this process (workers 1): a pool of renderers would spend seconds importing, for 30 small images.
SCENE = {"width": 160, "height": 120, "num_database": 24, "num_queries": 6, "texture_size": 64, "length": 20.0,
         "workers": 1, "seed": 4}  # fmt: skip

CALIBRATION = Calibration(
    features=0.1,
    pairs=0.01,
    map_pairs={"local_sfm": 0.002, "global_sfm": 0.004},
    registered_images={"local_sfm": 0.003, "global_sfm": 0.005},
    seconds=1.0,
    sample="a neighbourhood",
)


def plan() -> SfmPlan:
    local = ParadigmWork(
        "local_sfm", Work(40, 30), Work(20, 12), Work(6, 5), 3.0, Work(12, 10), Work(40, 36), Work(4, 4)
    )
    global_ = ParadigmWork(
        "global_sfm",
        Work(40, 30),
        Work(15, 15),
        Work(1, 1),
        15.0,
        Work(8, 8),
        Work(24, 24),
        Work(4, 4),
        shared_map=True,
    )
    return SfmPlan(Work(10, 8), [local, global_], exact=False)


def test_the_forecast_is_each_stage_s_units_times_its_calibrated_cost_spread_over_its_processes():
    seconds = forecast(plan(), CALIBRATION, processes=2, matching_device="cpu")
    assert seconds == pytest.approx(
        {
            "features": 8 * 0.1 / 2,
            "match + verify": (30 + 12 + 15) * 0.01 / 2,  # the query pairs shared by both paradigms, counted once
            "local_sfm: triangulate": 5 * 3 * 0.002 / 2,  # each query's maps, in the workers
            "local_sfm: register": 36 * 0.003 / 2,
            "global_sfm: triangulate": 15 * 0.004,  # the map every query shares, in one process
            "global_sfm: register": 24 * 0.005 / 2,
        }
    )
    on_gpu = forecast(plan(), CALIBRATION, processes=2, matching_device="cuda:0")
    assert on_gpu["match + verify"] == pytest.approx(57 * 0.01)  # one process feeds the device
    groundtruth = {GROUNDTRUTH_MATCHING: Work(50, 40), GROUNDTRUTH_MAP: Work(50, 50)}
    with_groundtruth = forecast(plan(), CALIBRATION, 2, "cpu", groundtruth)
    assert with_groundtruth[GROUNDTRUTH_MATCHING] == pytest.approx(40 * 0.01 / 2)
    assert with_groundtruth[GROUNDTRUTH_MAP] == pytest.approx(50 * 0.004)  # triangulated as the shared map is
    assert list(with_groundtruth)[:3] == ["features", GROUNDTRUTH_MATCHING, GROUNDTRUTH_MAP]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return dataclasses.replace(helpers.rendered_scene(tmp_path_factory.mktemp("scene"), SCENE), frustum_far=25.0)


def settings() -> BenchmarkSettings:
    config = helpers.evaluate_config("paradigms.local_sfm.k=[3,5]", "paradigms.global_sfm.k=[1,3]", "device=cpu")
    return benchmark_settings(config)


@pytest.mark.slow
def test_the_paradigms_match_at_most_the_pairs_the_ground_truth_left_and_share_its_map(scene, tmp_path):
    benchmark = settings()
    inputs = SfmInputs.prepare(scene, benchmark.sfm, tmp_path, extract=False)
    paradigms = benchmark.paradigms.sfm_paradigms()
    bounds = count_work(inputs, None, paradigms, num_rankings=5)
    config = helpers.evaluate_config("groundtruth.enabled=[relative_pose,co_observation]")
    groundtruth = validated(GroundTruthSettings, config.groundtruth, "groundtruth")
    database_pairs, query_pairs = groundtruth_sfm_pairs(scene, groundtruth, benchmark.sfm)
    assert database_pairs and query_pairs
    after, work = after_groundtruth(bounds, inputs, database_pairs, query_pairs)
    queries, database = len(scene.queries), len(scene.database)
    local, global_ = after.paradigms
    assert local.query_pairs.new == min(5 * queries * 5, queries * database - len(query_pairs))
    assert local.database_pairs.new == min(
        bounds.paradigms[0].database_pairs.new, comb(database, 2) - len(database_pairs)
    )
    assert global_.database_pairs.new == 0  # the global map's pairs are the ground truth's
    assert (local.registrations, local.maps) == (bounds.paradigms[0].registrations, bounds.paradigms[0].maps)
    pairs = len(database_pairs) + len(query_pairs)
    assert work == {GROUNDTRUTH_MATCHING: Work(pairs, pairs), GROUNDTRUTH_MAP: Work(pairs, pairs)}


def test_the_calibration_runs_the_pipeline_on_a_neighbourhood_and_leaves_nothing_behind(scene, tmp_path):
    sample, ranking = calibration_sample(scene)
    centres = scene.database.centers
    middle = np.argmin(np.linalg.norm(centres - centres.mean(0), axis=1))
    nearest = np.argsort(np.linalg.norm(centres - centres[middle], axis=1), kind="stable")[:CALIBRATION_DATABASE]
    assert sample.database.names == [scene.database.names[i] for i in nearest]
    assert len(sample.queries) == CALIBRATION_QUERIES and ranking.indices.shape == (3, CALIBRATION_DATABASE)
    distances = np.linalg.norm(sample.queries.centers[:, None] - sample.database.centers[None], axis=2)
    assert np.array_equal(ranking.indices, np.argsort(distances, axis=1, kind="stable"))  # nearest first
    benchmark = settings()
    calibration = calibrate(scene, benchmark.sfm, benchmark.paradigms.sfm_paradigms(), tmp_path / "cache")
    assert calibration.features > 0 and calibration.pairs > 0 and calibration.seconds > 0
    assert all(value > 0 for value in [*calibration.map_pairs.values(), *calibration.registered_images.values()])
    assert not any(path.is_file() for path in (tmp_path / "cache").rglob("*"))  # its scratch folder is gone


@pytest.mark.slow
def test_cached_work_is_forecast_as_cached_and_two_dry_runs_forecast_the_same(scene, tmp_path):
    """The rankings of a run whose work is all cached: counted exactly (no new work), forecast as
    reading it back, far below the forecast of the same work before it was done; the unit costs
    measured once and kept, so that a second dry run forecasts the same."""
    benchmark = settings()
    paradigms = benchmark.paradigms.sfm_paradigms()
    distances = np.linalg.norm(scene.queries.centers[:, None] - scene.database.centers[None], axis=2)
    nearest = np.argsort(distances, axis=1, kind="stable")[:, :10]
    rankings = [
        Ranking("near", nearest, -np.take_along_axis(distances, nearest, axis=1), "groundtruth"),
        random_ranking(len(scene.queries), len(scene.database), 10, 0),
    ]
    before = dry_run_forecast(scene, benchmark.sfm, paradigms, tmp_path, rankings, 0, (set(), set()))
    assert "measured now and kept in" in before[2] and before[0].new_pairs() > 0
    run_sfm(SfmInputs.prepare(scene, benchmark.sfm, tmp_path, extract=False), rankings, paradigms)  # fills the cache
    first = dry_run_forecast(scene, benchmark.sfm, paradigms, tmp_path, rankings, 0, (set(), set()))
    second = dry_run_forecast(scene, benchmark.sfm, paradigms, tmp_path, rankings, 0, (set(), set()))
    assert first[1] == second[1] and "read from" in first[2] and "read from" in second[2]
    plan = first[0]
    assert plan.exact and plan.features.new == 0 and plan.new_pairs() == 0
    assert all(w.maps.new == w.registrations.new == 0 and w.registrations.total for w in plan.paradigms)
    assert 0 < sum(first[1].values()) < 0.25 * sum(before[1].values())
    # how close the forecast comes to the cached run's time is benchmarks/bench_dry_run.py's to measure


def test_the_rankings_known_are_counted_exactly_and_the_others_bounded_a_shared_map_once(scene, tmp_path):
    benchmark = settings()
    paradigms = benchmark.paradigms.sfm_paradigms()
    inputs = SfmInputs.prepare(scene, benchmark.sfm, tmp_path, extract=False)
    known = [random_ranking(len(scene.queries), len(scene.database), 10, 0)]
    exact, bound = count_work(inputs, known, paradigms), count_work(inputs, None, paradigms, 2)
    mixed = counted_plan(inputs, known, paradigms, 2)
    assert not mixed.exact and mixed.features == exact.features
    for together, one, other in zip(mixed.paradigms, exact.paradigms, bound.paradigms):
        assert together.registrations == Work(
            one.registrations.total + other.registrations.total, one.registrations.new + other.registrations.new
        )
        shared = one.shared_map  # global_sfm's one map, whichever the rankings
        assert together.maps == (
            one.maps if shared else Work(one.maps.total + other.maps.total, one.maps.new + other.maps.new)
        )
    assert counted_plan(inputs, known, paradigms, 0) == exact and counted_plan(inputs, [], paradigms, 2) == bound
