"""The benchmarks keep running: each at a tiny size, its printed figures checked for shape.

Their timings are not tested (2 shared cores); `benchmarks/` prints them on demand.
"""

import re
import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"

TINY_RUNS = {
    "bench_approximation.py": (
        ["--queries", "300", "--database", "40", "--dimension", "16", "--depth", "5", "--check", "50"],
        [r"5 x\s+bdi, D=16:\s+[\d.]+ s", r"max difference \d\.\de-(0[7-9]|1\d)"],  # weights within 1e-6 of float64
    ),
    "bench_matching.py": (
        ["--keypoints", "300", "--repeats", "1", "--pipeline-images", "3"],
        [
            r"\s+300 \|\s+float32 \|\s+[\d.]+ \|\s+[\d.]+ \|\s+[\d.]+ "
            r"\|\s+[\d.]+ \| matcher: [\d.]+x the bare product's time",
            r"float16 at 300 keypoints: \d+\.\d\d % of float32's matches",
        ],
    ),
    "bench_groundtruth.py": (
        ["--queries", "40", "--database", "30", "--length", "30", "--width", "10"],
        [r"relative_pose:\s+[\d.]+ s", r"frustum:\s+[\d.]+ s"],
    ),
}


@pytest.mark.parametrize("script", sorted(TINY_RUNS))
def test_benchmark_runs_at_a_tiny_size(script):
    arguments, patterns = TINY_RUNS[script]
    result = subprocess.run(
        [sys.executable, str(BENCHMARKS / script), *arguments], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, result.stderr[-2000:]
    for pattern in patterns:
        assert re.search(pattern, result.stdout), f"{script}: no {pattern!r} in\n{result.stdout}"


@pytest.mark.slow
def test_training_benchmark_prints_the_loop_on_one_and_on_two_ddp_processes(tmp_path):
    from training_runs import SCENE, TINY_TRAINING

    tiny = [f"data.render.{key}={value}" for key, value in SCENE.items() if key != "conditions"]
    tiny += [override for override in TINY_TRAINING if not override.startswith("callbacks.")]
    tiny += [
        "model/backbone=torchvision",
        "model.backbone.name=resnet18",
        "model.weights=null",
        "model.random_init=true",
    ]
    result = subprocess.run(
        [sys.executable, str(BENCHMARKS / "bench_training.py"), "--ranks", "2", "--steps", "4", "--overrides"]
        + [f"paths.root_dir={tmp_path}", *tiny],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    for pattern in (
        r"loop on 1 process: [\d.]+ images/s \(batches of 14 images per process",
        r"loop on 2 processes: [\d.]+ images/s \(batches of 14 images per process, .*; 1 torch threads per process",
        r"2 processes: [\d.]+x the images/s of one",
    ):
        assert re.search(pattern, result.stdout), f"no {pattern!r} in\n{result.stdout}"
