"""The ``locretrieval`` command: installed from a wheel into a fresh environment it evaluates from an
empty folder, its outputs there, on a screen where log lines and bars never share a line; ``--help``
lists the subcommands and, per subcommand, its config groups; a dry run keeps no run folder."""

import fcntl
import os
import re
import shutil
import struct
import subprocess
import sys
import sysconfig
import termios
from pathlib import Path

import pytest
from helpers import STAMP, collisions

from locretrieval import commands

ROOT = Path(__file__).resolve().parents[1]
#: What `pip install <clone>` builds the wheel from.
SOURCES = ("pyproject.toml", "setup.py", "README.md", "locretrieval", "hydra_plugins", "configs")
#: A scene of 32 database images and 16 queries, paradigm 1 only: about 20 s of CPU.
TINY_RUN = [
    "paradigms.local_sfm.enabled=false",
    "paradigms.global_sfm.enabled=false",
    "groundtruth.enabled=[relative_pose]",
    "report.figure_formats=[]",
    "report.scene_view.enabled=false",
    "data.render.width=160",
    "data.render.height=120",
    "data.render.num_database=32",
    "data.render.num_queries=16",
    "data.render.texture_size=64",
    "data.render.length=20.0",
    "data.render.workers=1",
    "model.max_side=160",
    "model.step=4",
    "subsets.blur_width=160",
]


def in_terminal(command: list, cwd: Path, env: dict, columns: int = 120) -> tuple[int, str]:
    """``(exit status, screen)`` of ``command`` run in a pseudo-terminal of ``columns`` columns (its
    progress bars drawn, as a user sees them)."""
    leader, follower = os.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 40, columns, 0, 0))
    process = subprocess.Popen(command, cwd=cwd, env=env, stdin=follower, stdout=follower, stderr=follower)
    os.close(follower)
    chunks = []
    while True:
        try:
            chunk = os.read(leader, 65536)
        except OSError:  # the command ended: its side of the terminal is closed
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(leader)
    return process.wait(timeout=60), b"".join(chunks).decode("utf-8", "replace")


@pytest.mark.slow
def test_the_wheel_installs_a_command_that_evaluates_from_an_empty_folder_on_a_clean_screen(tmp_path):
    """The wheel of a copy of the clone, installed without an index into a fresh virtual environment
    that sees the lock's packages (this environment's site-packages, by a .pth file; its editable
    locretrieval is not processed from there), runs from a folder holding nothing, its outputs and
    cache there; in a terminal of 120 columns no log line shares a line with a bar, each line once."""
    clone = tmp_path / "clone"
    clone.mkdir()
    for name in SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, clone / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy(ROOT / name, clone / name)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--no-input", "--quiet"]
    subprocess.run(
        [*pip, "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", tmp_path, clone], check=True
    )
    [wheel] = tmp_path.glob("locretrieval-*.whl")
    environment = tmp_path / "env"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", environment], check=True)
    site = environment / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    (site / "lock.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    python, command = environment / "bin" / "python", environment / "bin" / "locretrieval"
    install = [*pip, "--python", python, "install", "--no-index", "--no-deps", "--ignore-installed", wheel]
    subprocess.run(install, check=True)
    empty = tmp_path / "empty"
    empty.mkdir()
    env = {key: value for key, value in os.environ.items() if not key.startswith(("LOCRETRIEVAL_", "HYDRA_", "PYTHON"))}
    where = [python, "-c", "import locretrieval; print(locretrieval.__file__)"]
    installed = subprocess.run(where, cwd=empty, env=env, capture_output=True, text=True, check=True).stdout
    assert Path(installed.strip()).is_relative_to(site)  # the wheel's package, not the clone's
    listed = subprocess.run([command, "--help"], cwd=empty, env=env, capture_output=True, text=True)
    assert listed.returncode == 0 and all(
        re.search(rf"^  {name} ", listed.stdout, re.M) for name in ("evaluate", "train", "export", "report")
    ), listed.stdout
    tiny = [*TINY_RUN[2:], "paradigms.local_sfm.k=[3]", "paradigms.global_sfm.k=[1,3]", "sfm.workers=2"]
    status, screen = in_terminal([command, "evaluate", *tiny], empty, env)
    assert status == 0, screen[-3000:]
    [results] = empty.glob("outputs/evaluate/synthetic_mall/densevlad/*/results.csv")
    assert (results.parent / "report.md").is_file() and (results.parent / "evaluate.log").is_file()
    assert {path.name for path in empty.iterdir()} == {"outputs", ".cache"}  # the cache below the current folder
    assert "%|" in screen and "match + verify" in screen  # bars were drawn
    assert collisions(screen) == [], collisions(screen)
    lines = [line.split(" - ", 1)[1] for line in re.split(r"[\r\n]+", screen) if STAMP.match(line) and " - " in line]
    repeated = {line for line in lines if lines.count(line) > 1}
    assert len(lines) > 10 and repeated == set(), repeated


def test_the_command_lists_its_subcommands_and_suggests_the_nearest(capsys):
    with pytest.raises(SystemExit) as ended:
        commands.main(["--help"])
    listed = capsys.readouterr().out
    assert ended.value.code == 0
    assert [line.split()[0] for line in listed.split("commands:\n")[1].split("\n\n")[0].splitlines()] == [
        "evaluate",
        "train",
        "export",
        "report",
    ]
    with pytest.raises(SystemExit) as ended:
        commands.main(["evalute", "model=netvlad"])
    assert ended.value.code == 2
    assert capsys.readouterr().err.startswith("locretrieval: unknown command 'evalute'; did you mean evaluate?")


def test_each_subcommand_s_help_lists_its_own_groups_with_the_chosen_option_first(capsys):
    commands.main(["evaluate", "--help"])
    evaluate = capsys.readouterr().out
    assert evaluate.startswith("usage: locretrieval evaluate [KEY=VALUE | GROUP=OPTION ...]")
    assert re.search(r"^  model +\[densevlad\] apgem boq ", evaluate, re.M)
    assert re.search(r"^  sfm/features +\[sift\] kapture$", evaluate, re.M)  # a nested group
    assert not re.search(r"^  (loss|optimizer|hydra/launcher) ", evaluate, re.M)  # train's and Hydra's
    commands.main(["train", "-h"])
    train = capsys.readouterr().out
    assert re.search(r"^  loss +\[listwise\] ap contrastive multi_similarity triplet$", train, re.M)
    assert re.search(r"^  debug +\[null\] quick$", train, re.M)  # an optional group none chose
    with pytest.raises(SystemExit) as ended:
        commands.main(["report", "--help"])
    assert ended.value.code == 0 and "usage: locretrieval report [-h]" in capsys.readouterr().out


def test_a_dry_run_of_the_command_line_keeps_no_run_folder(tmp_path):
    with commands.dry_run_folder(["data=baidu", "dry_run=true"]) as extra:
        folder = Path(re.fullmatch(r"hydra.run.dir='(.+)'", extra[0]).group(1))
        assert folder.is_dir() and extra[1:] == ["hydra.output_subdir=null"]
    assert not folder.exists()
    for arguments in (["dry_run=false"], ["-m", "dry_run=true"], ["data=baidu"]):
        with commands.dry_run_folder(arguments) as extra:
            assert extra == []


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
def test_make_evaluate_says_what_it_installs_and_shows_the_installation_as_it_goes(tmp_path):
    venv = tmp_path / "venv"  # a fresh environment: every installation step runs
    # --no-print-directory: under `make test` this make is a sub-make, which would name its folder last
    make = ["make", "--dry-run", "--no-print-directory", "evaluate", f"VENV={venv}"]
    completed = subprocess.run(make, cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert completed.returncode == 0, completed.stderr
    steps = completed.stdout.splitlines()
    sync = next(index for index, step in enumerate(steps) if "pip-sync" in step)
    assert not re.search(r"\s(--quiet|-q+)\b", steps[sync]), steps[sync]  # pip's own lines and bars, package by package
    assert steps[sync - 1].startswith("echo") and "Installing the packages of constraints.txt" in steps[sync - 1]
    assert "evaluate.py" in steps[-1]  # then the evaluation
