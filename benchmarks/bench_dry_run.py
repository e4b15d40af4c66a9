"""The dry run against the run it forecasts, as users run them (issue #59's targets: the dry run
takes at most a fifth of the run's SfM time, and the run's SfM time is within the band the dry run
states; issue #71's: with every SfM result cached, the run within 2x of its forecast, and two dry
runs forecast the same).

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
from dataclasses import dataclass
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
        cold = forecast_then_run(root, "cold", args.overrides)
        cached = forecast_then_run(root, "cached", args.overrides)  # every SfM result is in the cache now
        again = forecast_seconds(dry_forecast(root, "cached-again", args.overrides)[1])
    for label, result in (("empty SfM caches", cold), ("everything cached", cached)):
        print(
            f"{label}: dry run {result.dry_seconds:.1f} s (calibration {result.calibration:.1f} s), forecast "
            f"{result.forecast:.1f} s; the run's SfM work {result.measured:.1f} s; measured / forecast "
            f"{result.ratio:.2f} (band x{result.low:g}-{result.high:g}: "
            f"{'within' if result.low <= result.ratio <= result.high else 'OUTSIDE'})"
        )
    share = cold.dry_seconds / cold.measured
    print(
        f"dry run / run's SfM time {share:.2f} (target at most {DRY_RUN_SHARE:g}: "
        f"{'met' if share <= DRY_RUN_SHARE else 'MISSED'}); the cached run within 2x of its forecast: "
        f"{'met' if 0.5 <= cached.ratio <= 2 else 'MISSED'}; two dry runs of the cached run forecast "
        f"{cached.forecast:.2f} and {again:.2f} s: {'the same' if again == cached.forecast else 'DIFFERENT'}"
    )


@dataclass
class Forecast:
    """A dry run's forecast and the run it forecast: seconds, the band the dry run states."""

    dry_seconds: float
    calibration: float
    forecast: float
    low: float
    high: float
    measured: float  # the run's SfM work: the ground truth's seconds and the SfM paradigms'

    @property
    def ratio(self) -> float:
        return self.measured / self.forecast if self.forecast else float("inf")


def dry_forecast(root: Path, label: str, overrides: list[str]) -> tuple[float, str]:
    """A dry run's seconds and its log."""
    return run(root, "dry_run=true", f"hydra.run.dir={root / ('dry-run-' + label)}", *overrides)


def forecast_seconds(log: str) -> float:
    """The total a dry run's log forecasts."""
    return seconds_of(re.search(r"\n  total ([\d.]+ (?:s|min|h)):", log).group(1))


def forecast_then_run(root: Path, label: str, overrides: list[str]) -> Forecast:
    """A dry run, then the run it forecast (its ``summary.json``)."""
    dry_seconds, log = dry_forecast(root, label, overrides)
    forecast = forecast_seconds(log)
    low, high = (float(x) for x in re.search(r"\(x([\d.]+)-([\d.]+)\)", log).group(1, 2))
    calibration = re.search(r"calibrated in ([\d.]+) s", log)
    run(root, f"hydra.run.dir={root / ('run-' + label)}", *overrides)
    summary = json.loads((root / ("run-" + label) / "summary.json").read_text())
    measured = summary["ground truth seconds"] + summary["SfM seconds"]
    return Forecast(dry_seconds, float(calibration.group(1)) if calibration else 0.0, forecast, low, high, measured)


if __name__ == "__main__":
    main()
