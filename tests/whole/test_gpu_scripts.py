"""The prepared GPU scripts keep working: each rehearsed (the same steps at a tiny size on the CPU,
CUDA hidden), its output checked for shape, so that a session lent a GPU for minutes finds both
ready. The two rehearsals run side by side (about a minute each on 2 cores)."""

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[2]
#: train.yaml's report.gap rows, the metrics of every scene's gap.csv
GAP_METRICS = ["approximation/ewb/k3/5m_10deg", "local_sfm/pnp/k10/0.25m_2deg", "global_sfm/pnp/k5/0.25m_2deg"]
SCENES = ["mall_0", "mall_1", "mall_2", "street_0", "street_1"]


@pytest.fixture(scope="module")
def rehearsals(tmp_path_factory):
    """Both scripts started at once, each in its own folders: script -> (process, OUT, WORK)."""
    started = {}
    for script, how in (("gpu_check.sh", ["--rehearse"]), ("gpu_training_gain.sh", [])):
        root = tmp_path_factory.mktemp(script.removesuffix(".sh"))
        environment = {
            **os.environ,
            "OUT": str(root / "out"),
            "WORK": str(root / "work"),
            "LOCRETRIEVAL_CACHE": str(root / "cache"),
            "PYTHON": sys.executable,
            "PYTHONPATH": str(ROOT),
            **({} if how else {"REHEARSE": "1"}),  # the flag for one, the environment for the other
        }
        process = subprocess.Popen(
            ["bash", str(ROOT / "benchmarks" / script), *how],
            env=environment,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,  # its own process group: ended with every step it started
        )
        started[script] = (process, root / "out", root / "work")
    yield started
    for process, _, _ in started.values():
        if process.poll() is None:  # a test failed before waiting for it
            os.killpg(process.pid, signal.SIGKILL)


def finished(rehearsals, script: str) -> tuple[str, Path, Path]:
    """The script's log once it has ended with exit status 0, its OUT and WORK folders."""
    process, out, work = rehearsals[script]
    output, _ = process.communicate(timeout=600)
    assert process.returncode == 0, output[-4000:]
    log = (out / f"{script.removesuffix('.sh')}.txt").read_text()
    assert log.strip() and log in output  # the log holds what the steps printed
    return log, out, work


def step_lines(log: str) -> list[str]:
    """The summary lines of the steps after ``== steps``."""
    summary = log.split("== steps (seconds used of the GPU budget)\n")[1]
    return [line for line in summary.splitlines() if not line.startswith("==")]


@pytest.mark.slow
def test_gpu_check_rehearsal(rehearsals):
    log, _, work = finished(rehearsals, "gpu_check.sh")
    assert re.search(r"REHEARSAL on the CPU\ndevice: no CUDA GPU; torch \S+", log)
    for test in (
        "test_batched_matcher_on_the_gpu_equals_the_cpu_with_ties",
        "test_matching_on_the_gpu_stores_what_the_cpu_workers_store",
        "test_runs_on_the_configured_device",
    ):  # the CUDA tests, collected
        assert f"::{test}" in log
    for keypoints in (300, 600):  # two sizes as 5,000 and 20,000 on the GPU, beside the naive matcher
        assert re.search(rf"\s+{keypoints} \|\s+float32 \|( +[\d.]+ \|){{4}} matcher: [\d.]+x the bare", log)
    assert "baidu at scale 0.05: 34 database images x 115 queries" in log  # round(0.05 * (689, 2292))
    assert re.search(r"projected full SfM sweep \(baidu, 1,000 keypoints, \d+ processes\): [\d.]+ [sh]", log)
    assert re.search(r"slice measured end to end: [\d.]+ s .* measured / forecast [\d.]+", log)
    assert re.search(r"data pipeline alone \(no network\): \d+ images/s from the decoded cache", log)
    assert re.search(r"train.py loop: [\d.]+ images/s \([\d.]+x the bare step's time", log)
    results = pd.read_csv(work / "evaluate" / "results.csv")
    assert {"approximation", "local_sfm", "global_sfm"} <= set(results["paradigm"])
    lines = step_lines(log)
    assert [line.split("  ")[0] for line in lines] == [
        "CUDA tests",
        "bench_matching",
        "bench_scale baidu",
        "bench_training",
        "evaluate the built-in scene, SfM on the GPU",
    ]
    assert all(line.endswith("ok") for line in lines)
    budgets = sum(int(re.search(r"of +(\d+) s", line).group(1)) for line in lines)
    assert budgets <= 330 and f"budgets {budgets} s (rehearsal)" in log  # at most 5.5 min on the GPU


@pytest.mark.slow
def test_gpu_training_gain_rehearsal(rehearsals):
    log, out, work = finished(rehearsals, "gpu_training_gain.sh")
    # the rehearsal's recipe: 2 epochs of 2 batches (mining after the first), within its time limit
    assert re.search(r"checkpoint \S+last\.ckpt: 4 steps, in epoch 2\n", log)
    assert "hard negatives mined for" in log
    # the five scenes' databases (24 images each) and four more worlds, all their 24 + 6 images
    assert f"training on {5 * 24 + 4 * (24 + 6)} images" in log
    for scene in SCENES:
        gaps = pd.read_csv(work / "training_gain" / "scenes" / scene / "gap.csv")
        assert list(gaps["metric"]) == GAP_METRICS
        assert list(gaps["groundtruth"]) == ["gt_relative_pose", "gt_co_observation", "gt_relative_pose"]
        gap = gaps["groundtruth_value"] - gaps["densevlad"]
        # a share closed only where the ground truth is distinguishably above DenseVLAD (its interval above 0)
        exists = (gaps["gap_low_pts"] > 0).to_numpy()
        expected = np.where(exists, 100 * (gaps["trained"] - gaps["densevlad"]) / gap.where(gap > 0), np.nan)
        np.testing.assert_allclose(gaps["gap_closed_pct"], expected)
        assert all(note.startswith("no gap to close") for note in gaps.loc[~exists, "gap_note"])
        for column in ("densevlad", "untrained", "trained", "groundtruth_value"):
            assert gaps[column].between(0, 100).all()
    table = (out / "training_gain.md").read_text()
    assert table in log
    rows = [line for line in table.splitlines() if line.startswith("| ")][1:]
    labels = [row.split("|")[1].strip() for row in rows]  # report.py's summary: one trial marked best
    assert [label.removesuffix(" (best)") for label in labels] == [*SCENES, f"mean of {len(SCENES)}"]
    assert sum(label.endswith(" (best)") for label in labels) == 1
    lines = step_lines(log)
    assert len(lines) == 3 and all(line.endswith("ok") for line in lines)
    budgets = sum(int(re.search(r"of +(\d+) s", line).group(1)) for line in lines)
    assert f"budgets {budgets} s (rehearsal)" in log
