"""The dry run against the run it forecasts, as users run them (issue #59's targets: the dry run
takes at most a fifth of the run's SfM time, and the run's SfM time is within the band the dry run
states).

    .venv/bin/python benchmarks/bench_dry_run.py [--root DIR] [Hydra overrides for both runs ...]

The scene is rendered and DenseVLAD computed beforehand into the same root (untimed), the SfM
caches emptied; then ``python evaluate.py dry_run=true`` and ``python evaluate.py``, each timed as a
whole. The run's SfM time is what its ``summary.json`` holds: the ground truth's seconds (the
co-observation ground truth extracts the features and matches pairs first) and the SfM paradigms'
wall-clock seconds. The machine's load average is printed before each run: the forecast assumes
the machine stays as loaded as it was during the dry run's calibration.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: What the SfM stages and the ground truth cache, emptied before the runs are timed.
SFM_CACHES = ("features", "matches", "maps", "local_maps", "poses", "groundtruth")
#: The targets: the dry run's time over the run's SfM time at most this.
DRY_RUN_SHARE = 0.2


def run(root: Path, *overrides: str) -> tuple[float, str]:
    """``python evaluate.py`` with ``overrides``: its seconds and its log."""
    print(f"  load average {os.getloadavg()[0]:.2f}: python evaluate.py {' '.join(overrides)}", flush=True)
    started = time.perf_counter()
    done = subprocess.run(
        [sys.executable, str(ROOT / "evaluate.py"), f"paths.root_dir={root}", *overrides],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    seconds = time.perf_counter() - started
    if done.returncode:
        raise SystemExit(f"evaluate.py failed:\n{done.stderr[-3000:]}")
    return seconds, done.stdout + done.stderr


def seconds_of(text: str) -> float:
    """``12.3 s``, ``4.5 min`` or ``1.2 h`` as seconds."""
    value, unit = text.split()
    return float(value) * {"s": 1, "min": 60, "h": 3600}[unit]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, help="where the runs write (default: a temporary folder)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for both runs (e.g. a smaller scene)")
    args = parser.parse_args()
    machine = platform.processor() or platform.machine()
    print(f"machine: {machine}, {os.cpu_count()} cores, Python {platform.python_version()}")
    with tempfile.TemporaryDirectory(prefix="bench_dry_run-") as folder:
        root = args.root or Path(folder)
        run(
            root,
            f"hydra.run.dir={root / 'warm-up'}",
            "paradigms.local_sfm.enabled=false",
            "paradigms.global_sfm.enabled=false",
            "groundtruth.enabled=[relative_pose]",
            "report.figure_formats=[]",
            *args.overrides,
        )
        for cache in SFM_CACHES:
            shutil.rmtree(root / ".cache" / cache, ignore_errors=True)
        dry_seconds, log = run(root, "dry_run=true", f"hydra.run.dir={root / 'dry-run'}", *args.overrides)
        forecast = seconds_of(re.search(r"\n  total ([\d.]+ (?:s|min|h)):", log).group(1))
        low, high = (float(x) for x in re.search(r"\(x([\d.]+)-([\d.]+)\)", log).group(1, 2))
        calibration = float(re.search(r"calibrated in ([\d.]+) s", log).group(1))
        run_seconds, _ = run(root, f"hydra.run.dir={root / 'run'}", *args.overrides)
        summary = json.loads((root / "run" / "summary.json").read_text())
    groundtruth, paradigms = summary["ground truth seconds"], summary["SfM seconds"]
    measured = groundtruth + paradigms
    ratio = measured / forecast if forecast else float("inf")
    print(f"dry run: {dry_seconds:.1f} s in all, its calibration {calibration:.1f} s; forecast {forecast:.1f} s")
    print(
        f"run: {run_seconds:.1f} s in all, its SfM work {measured:.1f} s (ground truth {groundtruth:.1f} s, "
        f"SfM paradigms {paradigms:.1f} s)"
    )
    print(
        f"measured / forecast {ratio:.2f} (band x{low:g}-{high:g}: {'within' if low <= ratio <= high else 'OUTSIDE'}); "
        f"dry run / run's SfM time {dry_seconds / measured:.2f} (target at most {DRY_RUN_SHARE:g}: "
        f"{'met' if dry_seconds / measured <= DRY_RUN_SHARE else 'MISSED'})"
    )


if __name__ == "__main__":
    main()
