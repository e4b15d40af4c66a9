"""The main job (``python evaluate.py``, every default) at 1x, 2x and 4x the built-in scene at the
same density, each stage's cost per unit of its own work, and how that cost grows (issue #72's
targets: at most 1.25x from 1x to 4x for match + verify, local triangulation, both registrations and
the ground truth; the 4x run at most 5x the 1x run's CPU time; its peak memory at most 1.5x).

    .venv/bin/python benchmarks/bench_pipeline_scale.py [--sizes 1 2 4] [--root DIR] [Hydra overrides ...]

Size ``f`` renders ``f`` times the database images, queries and corridor length of
``configs/data/synthetic.yaml`` (128 / 64 / 48 m: 1x), so every query sees as many images around
it. Each size is rendered first (``dry_run=true``, untimed), then run once from empty caches but for
the rendered scene. Figures come from the run itself: its ``summary.json`` (each SfM stage's wall
and CPU seconds and work done, `locretrieval.sfm.pipeline.StageRecord`; the ground truth's) and its
``os.wait4`` resource usage (CPU time of the job and every worker process it waited for; peak
memory: the largest single process's resident set). CPU time is what the figures compare: wall time
on a shared machine says more about the other jobs. The load average is printed beside each run.

Units: the global descriptors per image, the ground truth per query (the database grows with the
queries: each query's neighbourhood, and the work on it, stays the same), the SfM features per
image, match + verify per pair matched and verified, local triangulation per map, registrations per
registration, the global map (one map of the whole database) per database image; the rest of the
run (start-up, the workers' starts, subsets, metrics, tables and report) as a whole.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: The scene's size keys (``data.render.<key>``) that grow with the size factor.
SIZE_KEYS = ("num_database", "num_queries", "length")
#: Targets: cost per unit at the largest size over the smallest, whole run's CPU time, peak memory.
UNIT_COST_TARGET, RUN_CPU_TARGET, MEMORY_TARGET = 1.25, 5.0, 1.5
#: The stages whose cost per unit has a target (an SfM stage's name ends with one of these; and the ground truth).
TARGETED = ("match + verify", "local_sfm: triangulate", "local_sfm: register", "global_sfm: register", "ground truth")
GROUND_TRUTH, DESCRIPTORS, OTHER = "ground truth", "descriptors", "the rest of the run"


@dataclass
class StageCost:
    """One stage of one run: wall and CPU ``seconds``, its work ``units`` in ``unit``."""

    wall: float
    cpu: float
    units: int
    unit: str

    @property
    def cpu_per_unit(self) -> float:
        return self.cpu / self.units if self.units else float("nan")


@dataclass
class RunCost:
    """One run of the main job: its scene (``database``, ``queries``), wall and CPU seconds, peak
    resident memory (bytes) of its largest process, the load average before and after, its stages
    and its pairs per query (`pairs_per_query`)."""

    factor: float
    database: int
    queries: int
    wall: float
    cpu: float
    peak_memory: int
    load: tuple[float, float]
    stages: dict[str, StageCost] = field(default_factory=dict)
    pairs: dict[str, float] = field(default_factory=dict)


def base_scene() -> dict[str, float]:
    """The built-in scene's size keys (``configs/data/synthetic.yaml``): 1x."""
    from omegaconf import OmegaConf

    render = OmegaConf.load(ROOT / "configs" / "data" / "synthetic.yaml").render
    return {key: render[key] for key in SIZE_KEYS}


def scene_overrides(base: dict[str, float], factor: float) -> list[str]:
    """``data.render`` overrides of ``factor`` times the base scene (counts rounded)."""
    return [
        f"data.render.{key}={round(value * factor) if isinstance(value, int) else value * factor}"
        for key, value in base.items()
    ]


def run_evaluate(arguments: list[str], cwd: Path) -> tuple[float, float, int]:
    """``python evaluate.py *arguments``: (wall seconds, CPU seconds of it and its waited-for
    processes, peak resident bytes of the largest of them); its error output on failure."""
    started = time.perf_counter()
    with tempfile.TemporaryFile() as errors:
        process = subprocess.Popen(
            [sys.executable, str(ROOT / "evaluate.py"), *arguments], cwd=cwd, stdout=subprocess.DEVNULL, stderr=errors
        )
        _, status, usage = os.wait4(process.pid, 0)
        process.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - started
        if process.returncode:
            errors.seek(0)
            raise SystemExit(f"evaluate.py {' '.join(arguments)} failed:\n{errors.read().decode()[-3000:]}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss * 1024


def measure(factor: float, base: dict[str, float], root: Path, overrides: list[str]) -> RunCost:
    """Render the scene of ``factor`` (untimed; kept in ``root`` for the next time), then run the
    main job on it from empty caches (a new folder of ``root``)."""
    scene = scene_overrides(base, factor)
    render = root / f"render-{factor:g}x"
    if not (render / ".cache" / "synthetic").is_dir():
        run_evaluate(
            [f"paths.root_dir={render}", f"hydra.run.dir={render / 'run'}", "dry_run=true", *scene, *overrides], ROOT
        )
    run = Path(tempfile.mkdtemp(prefix=f"run-{factor:g}x-", dir=root))
    (run / ".cache").mkdir()
    os.symlink(render / ".cache" / "synthetic", run / ".cache" / "synthetic")  # the rendered scene only
    load = os.getloadavg()[0]
    wall, cpu, peak = run_evaluate([f"paths.root_dir={run}", f"hydra.run.dir={run / 'run'}", *scene, *overrides], ROOT)
    summary = json.loads((run / "run" / "summary.json").read_text())
    cost = run_cost(factor, summary, wall, cpu, peak, (load, os.getloadavg()[0]))
    cost.pairs = pairs_per_query(run / "run")
    return cost


def pairs_per_query(run: Path) -> dict[str, float]:
    """The SfM paradigms' pairs to match per query, from a run's rankings (``rankings/*.npz``) and
    ks (``config.yaml``): each query with its top max(k) of every ranking (the query pairs) and the
    database pairs among its top max(k) of local SfM (its maps'), each pair once; with every
    ranking, and without the random baseline, whose pairs no other ranking shares."""
    from omegaconf import OmegaConf

    from locretrieval.paradigms.local_sfm import local_map_pairs
    from locretrieval.retrieval import EMPTY, Ranking

    paradigms = OmegaConf.load(run / "config.yaml").paradigms
    rankings = []
    for path in sorted((run / "rankings").glob("*.npz")):
        with np.load(path) as arrays:
            rankings.append(Ranking(str(arrays["name"]), arrays["indices"], arrays["scores"], str(arrays["kind"])))
    deepest, local = max(max(paradigms[name].k) for name in ("local_sfm", "global_sfm")), max(paradigms.local_sfm.k)
    found = {}
    for label, chosen in (
        ("every ranking", rankings),
        ("without random", [ranking for ranking in rankings if ranking.kind != "baseline"]),
    ):
        query_pairs = set()
        for ranking in chosen:
            top = ranking.indices[:, :deepest]
            rows, slots = np.nonzero(top != EMPTY)
            query_pairs.update(zip(rows.tolist(), top[rows, slots].tolist()))
        database_pairs = local_map_pairs(chosen, [[local]] * len(chosen))
        found[label] = (len(query_pairs) + len(database_pairs)) / rankings[0].num_queries
    return found


def run_cost(factor: float, summary: dict, wall: float, cpu: float, peak: int, load: tuple[float, float]) -> RunCost:
    """A run's `RunCost` from its ``summary.json``: each SfM stage in its own units (a map every
    query shares, one map, in the database images it holds), the ground truth per query."""
    database, queries = int(summary["database images"]), int(str(summary["queries"]).split()[0])
    stages = {}
    if "descriptors seconds" in summary:
        stages[DESCRIPTORS] = StageCost(
            summary["descriptors seconds"], summary["descriptors CPU seconds"], database + queries, "images"
        )
    stages[GROUND_TRUTH] = StageCost(
        summary["ground truth seconds"], summary.get("ground truth CPU seconds", float("nan")), queries, "queries"
    )
    for name, record in summary.get("SfM stages", {}).items():
        units, unit = int(record["done"]), record["unit"]
        if unit == "maps" and units == 1 and name.startswith("global_sfm"):  # the global map: by its images
            units, unit = database, "database images"
        stages[name] = StageCost(record["seconds"], record.get("cpu_seconds", float("nan")), units, unit)
    measured = sum(stage.cpu for stage in stages.values())
    stages[OTHER] = StageCost(float("nan"), cpu - measured, 1, "run")  # start-up, workers' starts, metrics, report
    return RunCost(factor, database, queries, wall, cpu, peak, load, stages)


def ratio(last: float, first: float) -> float:
    return last / first if first else float("nan")


def report(runs: list[RunCost]) -> list[str]:
    """The tables: per size its stages (wall, CPU, work, CPU per unit), then each cost per unit by
    size with the largest size's over the smallest's against its target, and the whole runs'."""
    lines = []
    for run in runs:
        lines += [
            f"{run.factor:g}x: {run.database} database images, {run.queries} queries; load average "
            f"{run.load[0]:.2f} before, {run.load[1]:.2f} after",
            f"  run: {run.wall:.1f} s wall, {run.cpu:.1f} s CPU, peak memory {run.peak_memory / 2**30:.2f} GiB",
            "  SfM pairs per query (query pairs and local maps' database pairs): "
            + ", ".join(f"{value:.1f} {label}" for label, value in run.pairs.items()),
            f"  {'stage':<24} | {'wall s':>7} | {'CPU s':>7} | {'work':>8} {'unit':<16} | CPU ms per unit",
        ]
        for name, stage in run.stages.items():
            lines.append(
                f"  {name:<24} | {stage.wall:7.1f} | {stage.cpu:7.1f} | {stage.units:8,} {stage.unit:<16} | "
                f"{1000 * stage.cpu_per_unit:.2f}"
            )
    first, last = runs[0], runs[-1]
    label = f"{last.factor:g}x / {first.factor:g}x"
    header = " | ".join(f"{run.factor:>7g}x" for run in runs)
    lines += ["", f"CPU ms per unit by size, and {label} (targets: <= {UNIT_COST_TARGET} where marked)"]
    lines.append(f"  {'stage':<24} | {header} | {label}")
    for name in first.stages:
        costs = [run.stages[name].cpu_per_unit if name in run.stages else float("nan") for run in runs]
        growth = ratio(costs[-1], costs[0])
        verdict = ""
        if name in TARGETED:
            verdict = "  met" if growth <= UNIT_COST_TARGET else "  MISSED"
        lines.append(f"  {name:<24} | {' | '.join(f'{1000 * cost:8.2f}' for cost in costs)} | {growth:.2f}{verdict}")
    cpu, memory = ratio(last.cpu, first.cpu), ratio(last.peak_memory, first.peak_memory)
    size = ratio(last.queries, first.queries)
    lines += [
        f"run CPU time {label}: {cpu:.2f} for {size:g}x the images (target at most {RUN_CPU_TARGET * size / 4:g}: "
        f"{'met' if cpu <= RUN_CPU_TARGET * size / 4 else 'MISSED'})",
        f"peak memory {label}: {memory:.2f} (target at most {MEMORY_TARGET}: "
        f"{'met' if memory <= MEMORY_TARGET else 'MISSED'})",
    ]
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=float, nargs="+", default=[1, 2, 4], help="size factors, smallest first")
    parser.add_argument("--root", type=Path, help="where the runs write, kept (default: a temporary folder)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every run")
    args = parser.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores", flush=True)
    base = base_scene()
    with tempfile.TemporaryDirectory(prefix="bench_pipeline_scale-") as folder:
        root = args.root or Path(folder)
        runs = []
        for factor in sorted(args.sizes):
            runs.append(measure(factor, base, root, args.overrides))
            print(f"{factor:g}x done: {runs[-1].wall:.1f} s wall, {runs[-1].cpu:.1f} s CPU", flush=True)
    print("\n".join(report(runs)))


if __name__ == "__main__":
    main()
