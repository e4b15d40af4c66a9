"""The job's ``shard`` key, and one evaluation's SfM work sharded over the jobs of Hydra's
launchers (joblib, submitit's local executor) as the README documents it, with the default
worker counts, then assembled by a plain run: the tables equal those of one plain run from an
empty cache, byte for byte."""

import gzip
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import evaluate as evaluate_here
from helpers import evaluate_config

from locretrieval import build
from locretrieval.config import ConfigError, refuse_moved_keys
from locretrieval.shard import Shard

ROOT = Path(__file__).resolve().parents[1]
#: A small scene; every worker count (rendering, SfM, figures) left at its default. 8 queries: two
#: shards of 4; 12 database images: local maps of the default ks and a global map. 100 bootstrap
#: resamples and a vocabulary from 20,000 RootSIFTs in 10 iterations: the runs' tables at a
#: fraction of the default's work (each of the 7 runs pays them).
SCENE = [
    "data.render.width=160",
    "data.render.height=120",
    "data.render.num_database=12",
    "data.render.num_queries=8",
    "data.render.texture_size=64",
    "data.render.length=20.0",
    "data.render.seed=5",
    "model.max_side=160",
    "model.step=4",
    "model.vocabulary_samples=20000",
    "model.kmeans_iterations=10",
    "metrics.uncertainty.resamples=100",
    "subsets.blur_width=160",
]
QUICK = [
    "groundtruth.enabled=[relative_pose]",
    "paradigms.local_sfm.k=[3,5]",  # two ks each: maps and registrations of several sizes, at most 5 images
    "paradigms.global_sfm.k=[1,5]",
    "output.ltvl=false",
    "report.figure_formats=[]",
    "report.scene_view.enabled=false",
]
TABLES = ("results.csv", "query_errors.csv.gz", "estimated_poses.csv.gz", "median_errors.csv")


def test_the_shard_is_a_key_of_the_job_parsed_once_and_checked_before_any_work(tmp_path, monkeypatch):
    assert Shard.parse("1/4", "shard") == Shard(1, 4) and Shard.parse(None, "shard") is None
    assert Shard(1, 4).take(list(range(10))) == [1, 5, 9] and str(Shard(1, 4)) == "1/4"
    for bad in ("4/4", "1-4", "a/4", 3):
        with pytest.raises(ConfigError, match=rf"^shard: must be 'i/n' with 0 <= i < n .*got {bad!r}"):
            Shard.parse(bad, "shard")
    # evaluate.py refuses a bad shard before it renders, describes or matches anything
    monkeypatch.setattr(build, "scene_of", lambda *args: pytest.fail("the scene was built"))
    with pytest.raises(ConfigError, match=r"^shard: must be 'i/n'"):
        build.build_evaluation(evaluate_config("shard=2/2", f"paths.root_dir={tmp_path}"))
    # the old spelling, a key of the sfm group, is refused naming the new one
    with pytest.raises(ConfigError, match=r"^sfm.shard: moved, now shard, a key of the job"):
        refuse_moved_keys(["sfm.shard=0/2"])
    with pytest.raises(ConfigError, match=r"^sfm.shard: moved, now shard"):
        build.build_evaluation(evaluate_config("+sfm.shard=0/2", f"paths.root_dir={tmp_path}"))


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


#: The reference run's own worker counts: everything in its process (see `unsharded`).
IN_THIS_PROCESS = ["data.render.workers=1", "sfm.workers=1"]


@pytest.fixture(scope="module")
def unsharded(tmp_path_factory) -> Path:
    """The run folder of one plain run from an empty cache: the reference the tables are compared with,
    run in this process (what evaluate.py runs, `helpers.evaluate`) and without worker processes: the
    launchers' jobs and the plain run that assembles their work are evaluate.py's processes with the
    default worker counts, as the README documents them; the reference only has to hold the same
    numbers, which do not depend on the worker processes (tests/test_threads.py, tests/sfm/test_pipeline.py),
    and it spares a process and its workers their imports (seconds each)."""
    root = tmp_path_factory.mktemp("unsharded")
    evaluate_here(evaluate_config(f"paths.root_dir={root}", *SCENE, *QUICK, *IN_THIS_PROCESS), root / "run")
    return root / "run"


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["joblib_local", "submitit_local"])
def test_shards_of_a_launcher_then_a_plain_run_equal_one_plain_run(tmp_path, unsharded, launcher):
    evaluate(
        "-m",
        f"hydra/launcher={launcher}",
        "shard=0/2,1/2",
        f"paths.root_dir={tmp_path}",
        f"hydra.sweep.dir={tmp_path / 'multirun'}",
    )
    shards = "".join(log.read_text() for log in sorted((tmp_path / "multirun").glob("*/evaluate.log")))
    assert "SfM shard 0/2: 4 of 8 queries" in shards and "SfM shard 1/2: 4 of 8 queries" in shards
    assert "rendering the synthetic scene" in shards  # by the renderer's processes, in a launcher's job
    assert not list((tmp_path / "multirun").glob("*/results.csv"))  # shards write no results
    assembled = evaluate(f"paths.root_dir={tmp_path}", f"hydra.run.dir={tmp_path / 'run'}")
    # everything was in the shared cache: nothing extracted, matched, triangulated or registered again
    for computed in ("local features (", "matching ", "new registration outcomes", "global map: "):
        assert computed not in assembled, computed
    for name in TABLES:
        assert table(tmp_path / "run" / name) == table(unsharded / name), name
