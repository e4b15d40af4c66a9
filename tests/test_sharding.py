"""One evaluation's SfM work sharded over the jobs of Hydra's joblib launcher, then assembled by a plain run."""

import gzip
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENE = [
    "data.render.width=160",
    "data.render.height=120",
    "data.render.num_database=20",
    "data.render.num_queries=8",
    "data.render.texture_size=64",
    "data.render.length=20.0",
    "data.render.workers=1",
    "data.render.seed=5",
    "model.max_side=160",
    "model.step=4",
    "subsets.blur_width=160",
]
QUICK = [
    "groundtruth.enabled=[relative_pose]",
    "output.ltvl=false",
    "report.figure_formats=[]",
    "report.scene_view.enabled=false",
    "hydra/launcher=joblib_local",
    "sfm.workers=1",
]
TABLES = ("results.csv", "query_errors.csv.gz", "estimated_poses.csv.gz", "median_errors.csv")


def evaluate(*overrides: str) -> str:
    """``evaluate.py`` with the overrides; its log."""
    completed = subprocess.run(
        [sys.executable, str(ROOT / "evaluate.py"), *overrides, *SCENE, *QUICK],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert completed.returncode == 0, completed.stderr[-3000:]
    return completed.stdout + completed.stderr


def table(path: Path) -> bytes:
    return gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()


def test_two_concurrent_shards_then_a_plain_run_equal_one_unsharded_run(tmp_path):
    # the reference: one job on the same launcher (its workers' thread count: the descriptors' k-means follows it)
    evaluate("-m", f"paths.root_dir={tmp_path / 'one'}", f"hydra.sweep.dir={tmp_path / 'one' / 'multirun'}")
    unsharded = next((tmp_path / "one" / "multirun").glob("*/results.csv")).parent

    shards = evaluate(
        "-m",
        f"paths.root_dir={tmp_path / 'two'}",
        f"hydra.sweep.dir={tmp_path / 'two' / 'multirun'}",
        "sfm.shard=0/2,1/2",
    )
    assert "SfM shard 0/2: 4 of 8 queries" in shards and "SfM shard 1/2: 4 of 8 queries" in shards
    assert not list((tmp_path / "two" / "multirun").glob("*/results.csv"))  # shards write no results
    assembled = evaluate(f"paths.root_dir={tmp_path / 'two'}", f"hydra.run.dir={tmp_path / 'two' / 'run'}")
    # everything was in the shared cache: nothing extracted, matched, triangulated or registered again
    for computed in ("local features (", "matching ", "new registration outcomes", "global map: "):
        assert computed not in assembled, computed
    for name in TABLES:
        assert table(tmp_path / "two" / "run" / name) == table(unsharded / name), name
