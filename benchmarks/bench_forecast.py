"""The SfM forecast against the measured time, per stage, as users run it (issue #48's target:
measured / forecast within [0.67, 1.5] per stage and in total on an otherwise idle machine).

    .venv/bin/python benchmarks/bench_forecast.py [--case evaluate training] [--root DIR] [ARGS for both ...]

- ``evaluate``: ``python evaluate.py`` as the README runs it (the synthetic mall, default workers),
  its SfM caches empty (the scene is rendered and DenseVLAD computed beforehand into the same root,
  untimed); the stages of its ``summary.json``.
- ``training``: ``python train.py`` for one short epoch, validated with the SfM paradigms before and
  after (``training.validation.max_queries=8 training.validation.sfm_max_keypoints=300``, as
  docs/training.md recommends for large scenes): each validation's stages from the run's
  ``summary.json`` (``references``: the reference, ground-truth and random rankings, with the
  local features; ``epoch -1`` and ``epoch 0``: the trained network's).

Each forecast is made by the run itself (`locretrieval.sfm.plan`): unit costs measured
on a sample of the scene just before, spread over the stages' worker processes. The machine's
load average is printed before each run: the forecast assumes the machine stays as loaded.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The training case's short run (a validation with SfM before and after one epoch of two batches).
TRAINING = [
    "trainer.max_epochs=1",
    "sampler.batches_per_epoch=2",
    "callbacks.localization_validation.sfm_every_n_epochs=1",
    "training.validation.max_queries=8",
    "training.validation.sfm_max_keypoints=300",
    "~logger",
]
#: What the SfM stages cache, emptied before the evaluate case is timed.
SFM_CACHES = ("features", "matches", "maps", "local_maps", "poses", "groundtruth")


def run(script: str, *overrides: str) -> None:
    print(f"  load average {os.getloadavg()[0]:.2f}: python {script} {' '.join(overrides)}", flush=True)
    done = subprocess.run([sys.executable, str(ROOT / script), *overrides], cwd=ROOT, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"{script} failed:\n{done.stderr[-3000:]}")


def print_stages(label: str, stages: dict) -> None:
    print(f"{label}:")
    print(f"  {'stage':<38} {'forecast':>9} {'measured':>9} {'measured / forecast':>20}")
    for stage, times in stages.items():
        forecast, measured, ratio = times["forecast_s"], times["measured_s"], times["ratio"]
        print(
            f"  {stage:<38} {'-' if forecast is None else f'{forecast:.1f} s':>9} "
            f"{'-' if measured is None else f'{measured:.1f} s':>9} {'-' if ratio is None else f'{ratio:.2f}':>20}"
        )


def evaluate_case(root: Path, extra: list[str]) -> None:
    run(
        "evaluate.py",
        f"paths.root_dir={root}",
        f"hydra.run.dir={root / 'warm-up'}",
        "paradigms.local_sfm.enabled=false",
        "paradigms.global_sfm.enabled=false",
        "groundtruth.enabled=[relative_pose]",
        "report.figure_formats=[]",
        *extra,
    )
    for cache in SFM_CACHES:
        shutil.rmtree(root / ".cache" / cache, ignore_errors=True)
    run("evaluate.py", f"paths.root_dir={root}", f"hydra.run.dir={root / 'evaluate'}", *extra)
    print_stages(
        "evaluate.py (SfM caches empty)", json.loads((root / "evaluate" / "summary.json").read_text())["SfM stages"]
    )


def training_case(root: Path, extra: list[str]) -> None:
    run("train.py", f"paths.root_dir={root}", f"output_dir={root / 'train'}", *TRAINING, *extra)
    validations = json.loads((root / "train" / "summary.json").read_text())["SfM stages per validation"]
    for validation, stages in validations.items():
        print_stages(f"train.py validation, {validation}", stages)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--case", nargs="+", choices=["evaluate", "training"], default=["evaluate", "training"])
    parser.add_argument("--root", type=Path, help="where the runs write (default: a temporary folder)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every run (e.g. a smaller scene)")
    args = parser.parse_args()
    machine = platform.processor() or platform.machine()
    print(f"machine: {machine}, {os.cpu_count()} cores, Python {platform.python_version()}")
    with tempfile.TemporaryDirectory(prefix="bench_forecast-") as folder:
        root = args.root or Path(folder)
        for case in args.case:
            {"evaluate": evaluate_case, "training": training_case}[case](root / case, args.overrides)


if __name__ == "__main__":
    main()
