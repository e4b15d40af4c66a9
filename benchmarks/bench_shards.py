"""A sharded evaluation against one plain run: the CPU time both spend, and their tables compared
byte for byte (issue #60's target: the shards and the run after them at most 1.15x one plain run's
CPU time, equal tables).

    .venv/bin/python benchmarks/bench_shards.py [--shards 2] [--root DIR] [Hydra overrides ...]

Both start from empty caches but for the rendered scene (rendered beforehand, untimed):

- ``plain``: ``python evaluate.py``;
- ``sharded``: ``python evaluate.py -m hydra/launcher=joblib_local 'shard=0/n,...'`` (the jobs at
  once, sharing one cache), then ``python evaluate.py``, which writes the results from the cache.

CPU time is user + system time of each command and every process it waited for (its workers),
from ``getrusage(RUSAGE_CHILDREN)``; wall time beside it. What the sharded evaluation adds is
mostly processes: the multirun's, one per job, each job's workers and the run after the jobs;
the CPU time a job and a worker spend starting (their imports) is printed too.
"""

from __future__ import annotations

import argparse
import gzip
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The tables compared byte for byte (``.gz`` files decompressed: gzip stores a time).
TABLES = ("results.csv", "median_errors.csv", "retrieval.csv", "groundtruth_statistics.csv", "query_errors.csv.gz")
#: The target: the sharded evaluation's CPU time over the plain run's at most this.
TARGET = 1.15


def timed(*arguments: str) -> tuple[float, float]:
    """``python evaluate.py *arguments``: its (CPU seconds, wall seconds)."""
    print(f"  load average {os.getloadavg()[0]:.2f}: python evaluate.py {' '.join(arguments)}", flush=True)
    before, started = resource.getrusage(resource.RUSAGE_CHILDREN), time.perf_counter()
    done = subprocess.run(
        [sys.executable, str(ROOT / "evaluate.py"), *arguments], cwd=ROOT, capture_output=True, text=True
    )
    wall, after = time.perf_counter() - started, resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode:
        raise SystemExit(f"evaluate.py failed:\n{done.stderr[-3000:]}")
    return after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime, wall


#: What a process of each kind imports before its first work: a job (Hydra, the evaluation, the default
#: model's module, pycolmap) and a worker (`locretrieval.pool.WORKERS`' preload and initializer).
STARTS = {
    "a job": "import hydra, pycolmap, locretrieval.evaluation, locretrieval.models.published.densevlad",
    "a worker": "import importlib\nfrom locretrieval.pool import WORKERS\n"
    "for module in WORKERS.preload:\n    importlib.import_module(module)\nWORKERS.initializer()",
}


def start_cost(code: str, repeats: int = 2) -> float:
    """The least CPU seconds of ``repeats`` fresh interpreters running ``code`` (their start)."""
    costs = []
    for _ in range(repeats):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        costs.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return min(costs)


def table_bytes(path: Path) -> bytes:
    return gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shards", type=int, default=2)
    parser.add_argument("--root", type=Path, help="where the runs write (default: a temporary folder)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every run (e.g. a smaller scene)")
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory(prefix="bench_shards-") as folder:
        root = args.root or Path(folder)
        render = root / "render"
        timed(f"paths.root_dir={render}", f"hydra.run.dir={render / 'run'}", "dry_run=true", *args.overrides)
        for label in ("plain", "sharded"):
            (root / label / ".cache").mkdir(parents=True)
            os.symlink(render / ".cache" / "synthetic", root / label / ".cache" / "synthetic")  # the scene, shared
        common = [f"paths.root_dir={root / 'sharded'}", *args.overrides]
        plain = timed(f"paths.root_dir={root / 'plain'}", f"hydra.run.dir={root / 'plain' / 'run'}", *args.overrides)
        shards = ",".join(f"{index}/{args.shards}" for index in range(args.shards))
        jobs = timed(
            "-m", "hydra/launcher=joblib_local", f"shard={shards}", f"hydra.sweep.dir={root / 'jobs'}", *common
        )
        after = timed(*common, f"hydra.run.dir={root / 'sharded' / 'run'}")
        runs = {"plain": root / "plain" / "run", "sharded": root / "sharded" / "run"}
        different = [
            name
            for name in TABLES
            if (runs["plain"] / name).exists()
            and table_bytes(runs["plain"] / name) != table_bytes(runs["sharded"] / name)
        ]
        compared = [name for name in TABLES if (runs["plain"] / name).exists()]
    sharded_cpu = jobs[0] + after[0]
    print(f"plain run: {plain[0]:.1f} s CPU, {plain[1]:.1f} s wall")
    print(
        f"{args.shards} shards then the plain run: {jobs[0]:.1f} + {after[0]:.1f} = {sharded_cpu:.1f} s CPU, "
        f"{jobs[1]:.1f} + {after[1]:.1f} s wall"
    )
    starts = {kind: start_cost(code) for kind, code in STARTS.items()}
    print("CPU time to start " + ", ".join(f"{kind}: {seconds:.1f} s" for kind, seconds in starts.items()))
    ratio = sharded_cpu / plain[0]
    print(
        f"sharded / plain CPU time {ratio:.2f} (target at most {TARGET}: {'met' if ratio <= TARGET else 'MISSED'}); "
        f"tables {'byte-identical' if not different else 'DIFFERENT: ' + ', '.join(different)} "
        f"({', '.join(compared)})"
    )


if __name__ == "__main__":
    main()
