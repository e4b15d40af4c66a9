"""The benchmarks keep running: each at a tiny size, its printed figures checked for shape.

Their timings are not tested (2 shared cores); `benchmarks/` prints them on demand.
"""

import re
import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"

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
        # the loop's figures, not its speed, are checked: half the scene's database, no validation
        # queries to speak of, and 48 x 36 training images (a quarter of the pixels of each step)
        "data.render.num_database=12",
        "data.render.num_queries=2",
        "datamodule.image_size=[48,36]",
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


def test_the_scaling_benchmark_divides_each_stage_by_its_own_work_and_compares_the_sizes(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import bench_pipeline_scale as scale

    def summary(database, queries, gt_cpu, stages):
        records = {
            name: {"seconds": cpu + 1, "cpu_seconds": cpu, "done": done, "unit": unit}
            for name, (cpu, done, unit) in stages.items()
        }
        return {
            "database images": database,
            "queries": f"{queries} ({queries} with reference poses)",
            "ground truth seconds": gt_cpu / 2,
            "ground truth CPU seconds": gt_cpu,
            "SfM stages": records,
        }

    small = summary(
        128,
        64,
        32.0,
        {
            "match + verify": (20.0, 10_000, "pairs"),
            "global_sfm: triangulate": (1.28, 1, "maps"),
            "global_sfm: register": (15.0, 1_500, "registrations"),
        },
    )
    large = summary(
        512,
        256,
        160.0,
        {
            "match + verify": (130.0, 50_000, "pairs"),
            "global_sfm: triangulate": (5.12, 1, "maps"),
            "global_sfm: register": (60.0, 6_000, "registrations"),
        },
    )
    runs = [
        scale.run_cost(1, small, 80.0, 200.0, 2**30, (1.0, 2.0)),
        scale.run_cost(4, large, 300.0, 1_100.0, 3 * 2**29, (2.0, 3.0)),
    ]
    assert runs[1].stages["global_sfm: triangulate"].units == 512  # one map of the whole database: per image
    assert runs[0].stages["ground truth"].cpu_per_unit == 0.5  # 32 s over 64 queries
    text = "\n".join(scale.report(runs))
    # per unit: pairs 2.00 -> 2.60 ms (1.30), the map 10 ms per image either way, registrations 10 ms (1.00),
    # the ground truth 500 -> 625 ms per query (1.25); the run 5.5x for 4x the images; memory 1.5x
    assert re.search(r"match \+ verify +\| +2\.00 \| +2\.60 \| 1\.30  MISSED", text), text
    assert re.search(r"global_sfm: triangulate +\| +10\.00 \| +10\.00 \| 1\.00\n", text), text
    assert re.search(r"global_sfm: register +\| +10\.00 \| +10\.00 \| 1\.00  met", text), text
    assert re.search(r"ground truth +\| +500\.00 \| +625\.00 \| 1\.25  met", text), text
    assert "run CPU time 4x / 1x: 5.50 for 4x the images (target at most 5: MISSED)" in text
    assert "peak memory 4x / 1x: 1.50 (target at most 1.5: met)" in text
