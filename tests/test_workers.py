"""Worker processes: small workloads stay in this process."""

import os

from locretrieval.localization import workers


def process_id(shared, task):
    return shared, task, os.getpid()


def test_a_small_workload_runs_in_this_process_without_starting_workers(monkeypatch):
    monkeypatch.setattr(workers, "_pools", workers.SpawnedPools(workers._pools.initializer))
    few = workers.MIN_TASKS_PER_WORKER * 2 - 1  # below the threshold for two workers
    results = list(workers.parallel_map(process_id, list(range(few)), 2, "test", shared="s"))
    assert results == [("s", task, os.getpid()) for task in range(few)]
    assert workers._pools.pools == {}  # no worker was spawned
