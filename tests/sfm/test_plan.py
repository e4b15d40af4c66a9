"""The SfM forecast: stages named as the run times them, spread over the processes the run gives
each stage, unit costs measured by the pipeline itself on a sample; every run reports forecast and
measured seconds per stage."""

import dataclasses
import json
import time

import helpers
import numpy as np
import pytest

from locretrieval.benchmark import BenchmarkSettings, sfm_plan
from locretrieval.paradigms import local_sfm
from locretrieval.retrieval import Ranking
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.pipeline import run_sfm
from locretrieval.sfm.plan import (
    MAP_SAMPLE_QUERIES,
    ParadigmWork,
    SfmPlan,
    UnitCosts,
    Work,
    _database_size,
    _stage_costs,
    forecast_sample,
    measure_unit_costs,
    prepare_workers,
)
from locretrieval.sfm.workers import MIN_TASKS_PER_WORKER

SCENE = {"width": 160, "height": 120, "num_database": 24, "num_queries": 6, "texture_size": 64, "length": 20.0,
         "workers": 2, "seed": 4}  # fmt: skip


def costs(**changes) -> UnitCosts:
    values = {
        "features": 0.1,
        "pairs": 0.01,
        "map_pairs": {"local_sfm": 0.002, "global_sfm": 0.004},
        "registrations": {"local_sfm": 0.003, "global_sfm": 0.005},
        "keypoints": 500.0,
        "device": "cpu",
        "sample": "a sample",
        "load": 0.0,
    }
    return UnitCosts(**{**values, **changes})


def paradigm_work(name: str, queries: int, parallel_maps: bool) -> ParadigmWork:
    return ParadigmWork(
        name,
        Work(100, 100),
        Work(300, 200),
        Work(40, 30),
        45.0,
        Work(90, 60),
        Work(500, 400),
        Work(queries, queries),
        parallel_maps,
    )


def test_the_forecast_spreads_each_stage_over_the_processes_the_run_gives_it():
    local, shared = paradigm_work("local_sfm", 20, True), paradigm_work("global_sfm", 20, False)
    # 64 new images: 4 tasks of 16 for 4 workers, too few for a pool not started: in this process
    plan = SfmPlan(Work(100, 64), [local, shared], True, 4, costs())
    stages = plan.forecast()
    assert stages["features"] == pytest.approx(64 * 0.1)
    assert stages["match + verify"] == pytest.approx((100 + 200 + 200) * 0.01)  # 4 tasks of 125: here too
    # 20 queries: enough tasks for the pool (MIN_TASKS_PER_WORKER * 4 = 16), spread over 4 workers
    assert 20 >= MIN_TASKS_PER_WORKER * 4
    assert stages["local_sfm: triangulate"] == pytest.approx(30 * 45.0 * 0.002 / 4)  # 20 queries' maps
    assert stages["local_sfm: register"] == pytest.approx(400 * 0.003 / 4)
    assert stages["global_sfm: triangulate"] == pytest.approx(30 * 45.0 * 0.004)  # one map, in this process
    assert stages["global_sfm: register"] == pytest.approx(400 * 0.005 / 4)
    assert list(stages) == [  # the order run_sfm runs them in: the shared map before the queries' stages
        "features",
        "match + verify",
        "global_sfm: triangulate",
        "local_sfm: triangulate",
        "local_sfm: register",
        "global_sfm: register",
    ]
    # a pool the run starts for its features (640 images: 20 tasks of 32) serves the small stages after it
    small = SfmPlan(Work(640, 640), [paradigm_work("local_sfm", 3, True)], True, 4, costs())
    assert small.forecast()["features"] == pytest.approx(640 * 0.1 / 4)
    assert small.forecast()["local_sfm: triangulate"] == pytest.approx(30 * 45.0 * 0.002 / 3)
    assert small.forecast()["local_sfm: register"] == pytest.approx(400 * 0.003 / 3)
    alone = SfmPlan(Work(64, 64), [paradigm_work("local_sfm", 3, True)], True, 4, costs())
    assert alone.forecast()["local_sfm: triangulate"] == pytest.approx(30 * 45.0 * 0.002)
    assert alone.forecast()["local_sfm: register"] == pytest.approx(400 * 0.003)
    assert small.pool_needed() and not alone.pool_needed()
    # a few tasks that would take long in one process: the pool is started for them, and they are spread
    long = SfmPlan(Work(64, 0), [paradigm_work("local_sfm", 3, True)], True, 4, costs(pairs=0.05))
    assert long.one_process_seconds()["match + verify"] == pytest.approx(300 * 0.05) and long.pool_needed()
    long.costs = costs(pairs=0.05, worker_start=2.0)  # what `prepare_workers` records
    assert long.forecast()["match + verify"] == pytest.approx(300 * 0.05 / 4)


def test_each_stage_adds_its_cost_per_call_where_it_has_new_work():
    per_call = {"match + verify": 0.5, "local_sfm: register": 0.2, "local_sfm: triangulate": 0.3}
    local = paradigm_work("local_sfm", 20, True)
    plan = SfmPlan(Work(100, 64), [local], True, 4, costs(per_call=per_call))
    stages = plan.forecast()
    assert stages["match + verify"] == pytest.approx((100 + 200) * 0.01 + 0.5)
    assert stages["local_sfm: register"] == pytest.approx(400 * 0.003 / 4 + 0.2)
    assert stages["features"] == pytest.approx(64 * 0.1)  # no cost per call measured for it
    cached = dataclasses.replace(local, maps=Work(40, 0), registrations=Work(90, 0), registered_images=Work(500, 0),
                                 queries=Work(20, 0))  # fmt: skip
    nothing_new = SfmPlan(Work(100, 0), [cached], True, 4, costs(per_call=per_call)).forecast()
    assert nothing_new["local_sfm: triangulate"] == 0 and nothing_new["local_sfm: register"] == 0
    # a stage without new work: its seconds looking for it, as the sample's runs without new units took
    idle = {"features": 0.004, "local_sfm: triangulate": 0.002}
    looking = SfmPlan(Work(100, 0), [cached], True, 4, costs(per_call=per_call, idle=idle)).forecast()
    assert looking == {"features": 0.004, "match + verify": nothing_new["match + verify"],  # its pairs are new
                       "local_sfm: triangulate": 0.002, "local_sfm: register": 0.0}  # fmt: skip
    assert "per stage call with new work: match + verify 500 ms" in plan.describe()


def test_the_stages_with_a_task_per_query_add_their_cost_per_task_spread_over_their_processes():
    per_task = {"local_sfm: triangulate": 0.01, "local_sfm: register": 0.02, "global_sfm: register": 0.03}
    local, shared = paradigm_work("local_sfm", 20, True), paradigm_work("global_sfm", 20, False)
    plain = SfmPlan(Work(100, 64), [local, shared], True, 4, costs()).forecast()
    plan = SfmPlan(Work(100, 64), [local, shared], True, 4, costs(per_task=per_task))
    assert plan.query_tasks() == {"local_sfm: triangulate": 20, "local_sfm: register": 20, "global_sfm: register": 20}
    # 20 queries with new work (the local maps: 20 of their 30 new maps' queries), over 4 workers
    assert {stage: seconds - plain[stage] for stage, seconds in plan.forecast().items()} == pytest.approx(
        {
            "features": 0,
            "match + verify": 0,
            "global_sfm: triangulate": 0,
            "local_sfm: triangulate": 20 * 0.01 / 4,
            "local_sfm: register": 20 * 0.02 / 4,
            "global_sfm: register": 20 * 0.03 / 4,
        }  # fmt: skip
    )
    assert plan.one_process_seconds()["local_sfm: register"] == pytest.approx(400 * 0.003 + 20 * 0.02)
    assert "per query: local_sfm: triangulate 10.0 ms, local_sfm: register 20.0 ms" in plan.describe()


def test_the_stages_the_pool_runs_add_a_call_of_the_pool():
    local, shared = paradigm_work("local_sfm", 20, True), paradigm_work("global_sfm", 20, False)
    plain = SfmPlan(Work(100, 64), [local, shared], True, 4, costs()).forecast()
    pooled = SfmPlan(Work(100, 64), [local, shared], True, 4, costs(pool_call=0.03)).forecast()
    # features and matching: 4 tasks each, in this process (the pool is not started for them);
    # the map every query shares: in this process; the per-query stages: 20 tasks, in the pool
    assert {stage: pooled[stage] - plain[stage] for stage in plain} == pytest.approx(
        {
            "features": 0,
            "match + verify": 0,
            "global_sfm: triangulate": 0,
            "local_sfm: triangulate": 0.03,
            "local_sfm: register": 0.03,
            "global_sfm: register": 0.03,
        }  # fmt: skip
    )


def test_a_call_of_the_pool_is_timed_in_its_workers_on_the_run_inputs(tmp_path, monkeypatch):
    """`prepare_workers` times a call of the pool when the run will use it: its two workers load
    the run's inputs."""
    from locretrieval.sfm import workers

    pools = workers.SpawnedPools(workers._pools.initializer)
    monkeypatch.setattr(workers, "_pools", pools)
    scene = helpers.rendered_scene(tmp_path / "scene", SCENE)
    settings = helpers.sfm_settings({"workers": 2})
    inputs = SfmInputs.prepare(scene, settings, tmp_path / "cache")  # both sets' features extracted
    alone = prepare_workers(SfmPlan(Work(30, 0), [], True, 2, costs()), inputs)
    assert alone.costs.pool_call == 0 and not pools.pools  # no stage needs the pool: not started, not timed
    try:
        needs_pool = SfmPlan(Work(640, 640), [], True, 2, costs())
        assert needs_pool.pool_needed()
        timed = prepare_workers(needs_pool, inputs).costs
        assert timed.worker_start > 0 and 0 < timed.pool_call < timed.worker_start
        assert list(workers.parallel_map(_database_size, range(4), 2, "a call", inputs)) == [len(scene.database)] * 4
    finally:
        pools.shutdown()


def test_the_costs_per_call_task_and_unit_are_the_plane_through_the_sample_runs():
    """(tasks, units, seconds) of runs: seconds = per call + tasks * per task + units * per unit."""
    exact = [(1, 10, 0.2 + 0.05 + 1.0), (1, 12, 0.2 + 0.05 + 1.2), (6, 60, 0.2 + 0.3 + 6.0), (8, 240, 0.2 + 0.4 + 24.0)]
    assert _stage_costs(exact) == pytest.approx((0.2, 0.05, 0.1))
    assert _stage_costs(exact[::-1]) == pytest.approx((0.2, 0.05, 0.1))  # any order
    # without tasks (features, matching): the line through (units, seconds)
    assert _stage_costs([(0, 10, 1.2), (0, 30, 3.2)]) == pytest.approx((0.2, 0.0, 0.1))
    # least squares of the residuals relative to each run's seconds (numpy's weighted line here)
    noisy = [(0, 10, 1.22), (0, 20, 2.16), (0, 30, 3.22)]
    units, seconds = np.array(noisy, dtype=float)[:, 1:].T
    slope, intercept = np.polyfit(units, seconds, 1, w=1 / seconds)
    assert _stage_costs(noisy) == pytest.approx((intercept, 0.0, slope))
    assert _stage_costs(noisy) != pytest.approx(tuple(np.polyfit(units, seconds, 1)[::-1]))  # not absolute
    # tasks in proportion to the units cannot be told from them, nor one task per run from a call: a line
    assert _stage_costs([(1, 10, 1.2), (3, 30, 3.2)]) == pytest.approx((0.2, 0.0, 0.1))
    assert _stage_costs([(1, 10, 1.2), (1, 30, 3.2)]) == pytest.approx((0.2, 0.0, 0.1))
    # noise that puts the intercept below zero: none, and the unit through the origin (relative least squares)
    relative_slope = (10 / 1.0 + 30 / 3.3) / (10**2 / 1.0**2 + 30**2 / 3.3**2)
    assert _stage_costs([(0, 10, 1.0), (0, 30, 3.3)]) == pytest.approx((0.0, 0.0, relative_slope), abs=1e-9)
    # or above the shortest run (more units in less time): at most that run's seconds, the unit at least 0
    per_call, _, per_unit = _stage_costs([(0, 10, 0.6), (0, 30, 0.5)])
    assert per_call == pytest.approx(0.5) and 0 <= per_unit < 1e-3
    # a negative cost per task (noise) is none, the others fitted without it
    slope, intercept = np.polyfit([10, 10, 30], [1.3, 1.2, 3.2], 1, w=[1 / 1.3, 1 / 1.2, 1 / 3.2])
    assert _stage_costs([(1, 10, 1.3), (2, 10, 1.2), (2, 30, 3.2)]) == pytest.approx((intercept, 0.0, slope))
    # runs without new units (the map every query shares, built once) only looked for work: left out
    assert _stage_costs([(0, 579, 0.06), (0, 0, 0.002), (0, 0, 0.001)]) == pytest.approx((0.0, 0.0, 0.06 / 579))
    assert _stage_costs([(0, 0, 0.0), (0, 0, 0.001)]) == (0.0, 0.0, 0.0)


def test_the_sample_tells_a_stage_cost_per_call_and_per_query_from_its_cost_per_unit(tmp_path, monkeypatch):
    """A register stage made 0.3 s slower per call (each run of the sample registers its new queries in one call)
    and 0.1 s per query: the measured cost per call grows by 0.3 s, per query by 0.1 s, the cost per registered
    image stays."""
    scene = dataclasses.replace(helpers.rendered_scene(tmp_path / "scene", SCENE), frustum_far=25.0)
    config = helpers.evaluate_config("paradigms.local_sfm.k=[3,5]", "paradigms.global_sfm.enabled=false", "device=cpu")
    settings = BenchmarkSettings.from_config(config)
    paradigms = settings.paradigms.sfm_stages()
    before = measure_unit_costs(scene, settings.sfm, paradigms, tmp_path / "before")
    local_stages = type(paradigms["local_sfm"])
    original = local_stages.register

    def slower_per_call(self, inputs, rankings, ks, folder, queries):
        if queries is not None:  # a chunk's registrations, not the gathering
            time.sleep(0.3)
        return original(self, inputs, rankings, ks, folder, queries)

    original_query = local_sfm.register_query_in_maps

    def slower_per_query(shared, task):
        time.sleep(0.1)
        return original_query(shared, task)

    monkeypatch.setattr(local_stages, "register", slower_per_call)
    monkeypatch.setattr(local_sfm, "register_query_in_maps", slower_per_query)
    after = measure_unit_costs(scene, settings.sfm, paradigms, tmp_path / "after")
    register = "local_sfm: register"
    assert after.per_call[register] - before.per_call.get(register, 0.0) == pytest.approx(0.3, abs=0.1)
    assert after.per_task[register] - before.per_task.get(register, 0.0) == pytest.approx(0.1, abs=0.04)
    # 8 registered images per query and ranking (k 3 and 5), 192 in the four runs (1, 1, 4 new queries, then 6
    # queries by 3 more rankings): 4 runs' 1.2 s per call would be 6 ms each, 12 queries' 1.2 s 6 ms each
    assert after.registrations["local_sfm"] == pytest.approx(before.registrations["local_sfm"], abs=3e-3)
    assert after.sample == "24 database images and 1 then 2 then 6 of its queries, then those by 3 more rankings"


def test_the_sample_is_a_neighbourhood_ranked_by_its_queries(tmp_path):
    scene = helpers.rendered_scene(tmp_path, SCENE)
    sample, ranking = forecast_sample(scene, 10, 2)
    assert len(sample.database) == 10 and len(sample.queries) == 2
    assert set(sample.database.names) <= set(scene.database.names)
    centres = sample.database.centers
    assert (
        np.linalg.norm(centres - centres[0], axis=1).max()
        <= np.linalg.norm(scene.database.centers - centres[0], axis=1).max()
    )
    distances = np.linalg.norm(sample.queries.centers[:, None] - centres[None], axis=2)
    assert np.array_equal(ranking.indices, np.argsort(distances, axis=1, kind="stable"))
    assert isinstance(ranking, Ranking) and ranking.depth == 10


def test_forecast_and_run_name_the_same_stages_and_the_units_come_from_the_pipeline(tmp_path, monkeypatch):
    scene = dataclasses.replace(helpers.rendered_scene(tmp_path / "scene", SCENE), frustum_far=25.0)
    config = helpers.evaluate_config("paradigms.local_sfm.k=[3,5]", "paradigms.global_sfm.k=[1,3]", "device=cpu")
    settings = BenchmarkSettings.from_config(config)
    order = np.argsort(
        np.linalg.norm(scene.queries.centers[:, None] - scene.database.centers[None], axis=2), axis=1, kind="stable"
    )
    rankings = [Ranking("nearest", order[:, :8], -np.arange(8.0)[None].repeat(len(order), 0), "groundtruth")]
    calls = []
    monkeypatch.setattr("locretrieval.sfm.plan.run_sfm", lambda *a, **k: calls.append(a) or run_sfm(*a, **k))
    plan = sfm_plan(scene, rankings, settings, tmp_path / "cache")
    # the sample's runs of the stages: its first query, then one more, then every one (the cost per call apart),
    # then every one by three more rankings, random orders of its images (the cost per query apart)
    assert [(call[0].name.endswith("(forecast sample)"), len(call[0].queries), len(call[1])) for call in calls] == [
        (True, 1, 1), (True, 2, 1), (True, 6, 1), (True, 6, 4)]  # fmt: skip
    assert calls[0][0].queries.names == calls[1][0].queries.names[:1] == calls[2][0].queries.names[:1]
    assert calls[3][0].queries.names == calls[2][0].queries.names
    first, *more = calls[3][1]
    assert np.array_equal(first.indices, calls[2][1][0].indices)
    assert all(np.array_equal(np.sort(ranking.indices, axis=1), np.sort(first.indices, axis=1)) for ranking in more)
    assert len({first.indices.tobytes(), *(ranking.indices.tobytes() for ranking in more)}) == 4
    assert not list((tmp_path / "cache").glob(".forecast*"))  # its scratch folder is gone
    # the global map is built in the first run: the others only looked for its work
    assert plan.costs.idle["global_sfm: triangulate"] > 0 and "global_sfm: triangulate" not in plan.costs.per_call
    measured = {}
    run_sfm(scene, rankings, settings.paradigms.sfm_stages(), settings.sfm, tmp_path / "cache", measured)
    assert set(plan.forecast()) == set(measured)
    assert all(value >= 0 for value in plan.forecast().values())


@pytest.mark.slow
def test_evaluate_writes_forecast_and_measured_seconds_per_stage_to_its_summary(tmp_path):
    from locretrieval.evaluation import evaluate

    tiny = [f"data.render.{key}={value}" for key, value in SCENE.items()]
    config = helpers.evaluate_config(
        f"paths.root_dir={tmp_path}",
        *tiny,
        "model.max_side=160",
        "model.step=4",
        "subsets.blur_width=160",
        "groundtruth.enabled=[relative_pose]",
        "paradigms.local_sfm.k=[3,5]",
        "paradigms.global_sfm.k=[1,3]",
        "report.figure_formats=[]",
        "report.scene_view.enabled=false",
        "output.ltvl=false",
        "device=cpu",
    )
    evaluate(config, tmp_path / "run")
    stages = json.loads((tmp_path / "run" / "summary.json").read_text())["SfM stages"]
    assert set(stages) == {
        "features",
        "match + verify",
        "local_sfm: triangulate",
        "local_sfm: register",
        "global_sfm: triangulate",
        "global_sfm: register",
        "total",
    }
    for times in stages.values():
        assert times["measured_s"] is not None and times["measured_s"] >= 0
        assert times["forecast_s"] is not None and times["forecast_s"] >= 0
    total = stages["total"]
    assert total["ratio"] == pytest.approx(total["measured_s"] / total["forecast_s"])


def test_with_the_maps_inputs_cached_the_global_registrations_are_timed_on_the_whole_map(tmp_path, monkeypatch):
    """The registration unit of a map every query shares depends on the rankings and on the map
    (LO-RANSAC's time per correspondence grows as the inlier ratio falls): with the run's rankings
    and the map's features and matches cached, it is timed on that map, on the run's own work,
    which the plan then leaves out."""
    scene = dataclasses.replace(helpers.rendered_scene(tmp_path / "scene", SCENE), frustum_far=25.0)
    config = helpers.evaluate_config("paradigms.local_sfm.k=[3,5]", "paradigms.global_sfm.k=[1,3]", "device=cpu")
    settings = BenchmarkSettings.from_config(config)
    paradigms, cache = settings.paradigms.sfm_stages(), tmp_path / "cache"
    order = np.argsort(
        np.linalg.norm(scene.queries.centers[:, None] - scene.database.centers[None], axis=2), axis=1, kind="stable"
    )
    nearest = Ranking("nearest", order[:, :8], -np.arange(8.0)[None].repeat(len(order), 0), "groundtruth")
    cold = measure_unit_costs(scene, settings.sfm, paradigms, cache, [nearest])
    assert cold.registrations_on_map == {}  # nothing cached: the sample's unit stands
    run_sfm(scene, [nearest], paradigms, settings.sfm, cache)  # features, map pairs and the map cached now

    shuffled = Ranking("far first", order[:, ::-1][:, :8].copy(), -np.arange(8.0)[None].repeat(6, 0), "descriptor")
    registered = []
    global_stages = type(paradigms["global_sfm"])
    original = global_stages.register
    monkeypatch.setattr(
        global_stages,
        "register",
        lambda self, inputs, rankings, ks, folder, queries: (
            registered.append((folder, queries and list(queries), ks))
            or original(self, inputs, rankings, ks, folder, queries)
        ),
    )
    rankings = [nearest, shuffled]
    assert paradigms["global_sfm"].plan(scene, rankings, settings.sfm, cache, 0).registrations.new > 0
    monkeypatch.setattr("locretrieval.benchmark._unit_costs", {})  # measured afresh, as in a new process
    plan = sfm_plan(scene, rankings, settings, cache)
    costs = plan.costs
    assert set(costs.registrations_on_map) == {"global_sfm"}  # local maps are per query: the sample's unit
    assert costs.registrations_on_map["global_sfm"] == "6 queries and the run's rankings (2) on the whole map"
    assert costs.registrations["global_sfm"] > 0
    # the sample's runs register theirs in its temporary folder; the map's measurement 6 of 6 in the run's cache
    ((queries, ks),) = [(call[1], call[2]) for call in registered if call[0] == cache]
    assert queries == list(range(MAP_SAMPLE_QUERIES)) == list(range(len(scene.queries))) and ks == [[1, 3], [1, 3]]
    # what it did is the run's own work: the plan, counted after it, has no global registration left
    work = {paradigm.paradigm: paradigm for paradigm in plan.paradigms}
    assert work["global_sfm"].registrations.new == 0 and work["global_sfm"].maps.new == 0
    assert work["local_sfm"].registrations.new > 0  # the shuffled ranking's local maps are still to do
    assert (
        "timed on 6 queries and the run's rankings (2) on the whole map"
        in SfmPlan(Work(0, 0), [], True, 2, costs).describe()
    )
    without_rankings = measure_unit_costs(scene, settings.sfm, paradigms, cache)  # dry_run: no rankings yet
    assert without_rankings.registrations_on_map == {}
