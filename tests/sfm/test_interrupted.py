"""A run killed (SIGKILL) in the middle of a paradigm loses no finished registration: the rerun
registers only what had not been saved, and its tables equal an uninterrupted run's."""

import gzip
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from locretrieval.cache import load_arrays

ROOT = Path(__file__).resolve().parents[2]
#: Enough registrations (128 queries x 3 rankings x k = 5, 10, 15, 20) for local SfM's register stage,
#: which reads maps triangulated before it, to run several save intervals (`SAVE_SECONDS`).
COMMAND = [
    "data.render.width=160",
    "data.render.height=120",
    "data.render.num_database=30",
    "data.render.num_queries=128",
    "data.render.texture_size=64",
    "data.render.length=24.0",
    "data.render.seed=3",
    "model.max_side=160",
    "model.step=4",
    "subsets.blur_width=160",
    "groundtruth.enabled=[relative_pose]",
    "paradigms.global_sfm.enabled=false",
    "paradigms.local_sfm.k=[5,10,15,20]",
    "output.ltvl=false",
    "report.figure_formats=[]",
    "report.scene_view.enabled=false",
]
TABLES = ("results.csv", "query_errors.csv.gz", "estimated_poses.csv.gz")
pytestmark = pytest.mark.slow


def evaluate(root: Path, run: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, str(ROOT / "evaluate.py"), f"paths.root_dir={root}", f"hydra.run.dir={root / run}", *COMMAND],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # its worker processes are killed with it
    )


def finished(process: subprocess.Popen) -> str:
    output, _ = process.communicate(timeout=900)
    assert process.returncode == 0, output[-3000:]
    return output


def saved_outcomes(root: Path) -> int:
    """Registration outcomes on disk: the distinct keys of every part of the local-SfM pose cache."""
    parts = list((root / ".cache" / "poses").glob("local_sfm-*/[!.]*.npz"))
    return len({key.tobytes() for part in parts for key in load_arrays(part)["keys"]})


def table(path: Path) -> bytes:
    return gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()


def test_a_run_killed_mid_paradigm_loses_no_saved_registration(tmp_path):
    killed = evaluate(tmp_path, "killed")
    while not list((tmp_path / ".cache" / "poses").glob("local_sfm-*/[!.]*.npz")):
        assert killed.poll() is None, killed.communicate()[0][-3000:]
        time.sleep(0.05)
    os.killpg(killed.pid, signal.SIGKILL)
    killed.communicate()
    before = saved_outcomes(tmp_path)
    assert before > 0

    rerun = finished(evaluate(tmp_path, "rerun"))
    registered = sum(int(n) for n in re.findall(r"(\d+) new registration outcomes saved to \S*local_sfm-", rerun))
    total = saved_outcomes(tmp_path)
    assert registered > 0 and before + registered == total  # only what the killed run had not saved

    # an uninterrupted run (features, matches and maps cached; every registration again) gives the same tables
    poses = next((tmp_path / ".cache" / "poses").glob("local_sfm-*"))
    poses.rename(poses.with_name("set-aside"))
    again = finished(evaluate(tmp_path, "uninterrupted"))
    assert f"{total} new registration outcomes saved" in again
    for name in TABLES:
        assert table(tmp_path / "rerun" / name) == table(tmp_path / "uninterrupted" / name), name
