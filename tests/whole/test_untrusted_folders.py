"""Folders someone shares, run as users meet them: photo folders whose links loop,
COLMAP models that lie (a focal length of 0, a NaN quaternion), GPS
altitudes of 4.29e9 m, and folders to write into holding planted links (an export's config.yaml and
hloc/, a sweep's optuna.db or optuna.journal). Each command runs in a fresh interpreter (a crash
cannot take the test run with it), all at once: each must end in a named error and exit status 1
within seconds and 1 GiB of memory of its own, or succeed, and nothing is written outside."""

import contextlib
import os
import re
import resource
import shutil
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import CONFIGS
from own_place import plain_photos, write_model

from locretrieval.scene import Camera

ROOT = CONFIGS.parent
#: The address space of each command (torch, its CUDA bindings and pycolmap's reserve over 4 GiB of it).
MEMORY_CAP = 8 * 2**30
#: The memory of its own (anonymous: not the pages of the libraries' files, which the kernel maps
#: more or fewer of from machine to machine) each command and its workers may reach: importing torch,
#: Hydra and pycolmap takes about 0.55 GiB of it; the reproductions reached 2.27 and 3.4 GB, or hung.
ANONYMOUS_MIB = 1024
#: CPU seconds each command may take (importing torch, Hydra and pycolmap: about 9 s of it; a symlink
#: loop hung, a photo folder ran 287 s to a MemoryError). Measured in CPU time, not on the clock:
#: the commands run at once on a machine other test processes share.
WITHIN = 40


def colmap_place(root: Path, altitude: float | None = None) -> tuple[Path, Path]:
    """15 flat photos 8 x 6 along 14 m (GPS at their centres, at ``altitude`` when given) and
    their binary COLMAP model (metres, identity rotations, no 3D points): ``(model, photos)``."""
    centres = np.column_stack([np.linspace(0.0, 14.0, 15), 3.0 * np.sin(np.arange(15)), np.zeros(15)])
    names = plain_photos(root / "photos", centres, 8, 6, None if altitude is None else [altitude] * 15)
    camera = Camera("PINHOLE", 8, 6, (6.0, 6.0, 4.0, 3.0))
    write_model(root / "sparse", names, camera, np.tile([1.0, 0.0, 0.0, 0.0], (15, 1)), -centres, [], np.zeros((0, 3)))
    return root / "sparse", root / "photos"


def patched(path: Path, offset: int, layout: str, *values) -> None:
    data = bytearray(path.read_bytes())
    struct.pack_into(layout, data, offset, *values)
    path.write_bytes(bytes(data))


def anonymous_mib(pid: int) -> float:
    """The anonymous resident memory of a process and its descendants now (0 once it has ended)."""
    total = 0.0
    with contextlib.suppress(OSError):
        anonymous = re.search(r"RssAnon:\s+(\d+) kB", Path(f"/proc/{pid}/status").read_text())
        total += float(anonymous.group(1)) / 1024 if anonymous else 0.0  # none once it is a zombie
        for child in Path(f"/proc/{pid}/task/{pid}/children").read_text().split():
            total += anonymous_mib(int(child))
    return total


def run_at_once(commands: dict[str, list[str]], logs: Path) -> dict[str, tuple[int, str, float, float]]:
    """Each command in a fresh process under `MEMORY_CAP`, all started together: ``name -> (exit
    status, output, CPU seconds, peak anonymous MiB of it and its workers, sampled every 0.2 s)``;
    a command still running after 10 minutes hung."""

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))

    environment = {**os.environ, "PYTHONPATH": str(ROOT)}
    logs.mkdir()
    deadline, running = time.monotonic() + 600, {}
    for name, command in commands.items():
        with (logs / f"{name}.log").open("w") as output:
            process = subprocess.Popen(
                command, cwd=ROOT, env=environment, stdout=output, stderr=subprocess.STDOUT, preexec_fn=cap
            )
        running[process.pid] = name
    finished, peaks = {}, dict.fromkeys(running, 0.0)
    while running:
        assert time.monotonic() < deadline, f"still running: {sorted(running.values())}"
        pid, status, usage = os.wait4(-1, os.WNOHANG)
        if pid == 0:
            for running_pid in running:
                peaks[running_pid] = max(peaks[running_pid], anonymous_mib(running_pid))
            time.sleep(0.2)
        elif pid in running:
            name = running.pop(pid)
            cpu_seconds = usage.ru_utime + usage.ru_stime
            exit_status = os.waitstatus_to_exitcode(status)
            finished[name] = (exit_status, (logs / f"{name}.log").read_text(), cpu_seconds, peaks[pid])
    return finished


@pytest.mark.slow
def test_shared_folders_end_in_a_named_error_or_succeed_writing_nothing_outside(tmp_path):
    model, photos = colmap_place(tmp_path / "place")
    (photos / "a").symlink_to(".")
    (photos / "b").symlink_to(".")
    bad = {name: shutil.copytree(model, tmp_path / name) for name in ("focal", "quaternion")}
    patched(bad["focal"] / "cameras.bin", 8 + 24, "<2d", 0.0, 0.0)  # PINHOLE fx, fy of camera 1
    patched(bad["quaternion"] / "frames.bin", 8 + 8, "<d", float("nan"))  # qw of frame 1
    high_model, high_photos = colmap_place(tmp_path / "high", altitude=4294967295.0)  # 2^32 - 1 m: a field wrapped
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no photos")
    (empty / "a").symlink_to(".")
    (empty / "b").symlink_to(".")
    victim, other, elsewhere = tmp_path / "victim.yaml", tmp_path / "other", tmp_path / "elsewhere"
    victim.write_text("kept\n")
    other.mkdir()
    elsewhere.mkdir()
    (elsewhere / "journal").write_text("kept\n")
    export_dir, sqlite_dir, journal_dir = tmp_path / "export", tmp_path / "sweep_sqlite", tmp_path / "sweep_journal"
    for folder in (export_dir, sqlite_dir, journal_dir):
        folder.mkdir()
    (export_dir / "config.yaml").symlink_to(victim)
    (export_dir / "hloc").symlink_to(other)
    (sqlite_dir / "optuna.db").symlink_to(elsewhere / "x.db")
    (journal_dir / "optuna.journal").symlink_to(elsewhere / "journal")

    def entry(script: str, name: str, *overrides: str) -> list[str]:
        where = [f"hydra.run.dir={tmp_path / 'runs' / name}", f"paths.cache_dir={tmp_path / 'cache' / name}"]
        return [sys.executable, str(ROOT / script), *overrides, *where]

    def colmap(name: str, model: Path, images: Path, *overrides: str) -> list[str]:
        return entry("evaluate.py", name, "data=colmap", f"data.model={model}", f"data.images={images}", *overrides)

    quick = ("dry_run=true", "paradigms.local_sfm.enabled=false", "paradigms.global_sfm.enabled=false")
    sweep = ("-m", "hparams_search=localization")
    commands = {
        "loops, colmap": colmap("loops", model, photos, "data.metres_per_unit=1", *quick),
        "loops, photos": entry("evaluate.py", "photos", "data=photos", f"data.images={empty}"),
        "focal 0": colmap("focal", bad["focal"], photos, "data.metres_per_unit=1"),
        "nan quaternion": colmap("quaternion", bad["quaternion"], photos, "data.metres_per_unit=1"),
        "gps altitude": colmap("gps", high_model, high_photos),
        "export links": [sys.executable, str(ROOT / "export.py"), f"hydra.run.dir={export_dir}"],
        "sweep, sqlite": [sys.executable, str(ROOT / "train.py"), *sweep, f"hydra.sweep.dir={sqlite_dir}"],
        "sweep, journal": [
            sys.executable, str(ROOT / "train.py"), *sweep, f"hydra.sweep.dir={journal_dir}",
            "hydra.sweeper.storage=journal",
        ],
    }  # fmt: skip
    expected = {
        "loops, colmap": (0, r"2 links to folders inside it are not followed.*dry run: no SfM paradigm is enabled"),
        "loops, photos": (1, rf"{empty}: no image files \(extensions"),
        "focal 0": (1, r"focal/cameras\.bin: camera 1: focal length\(s\) \[0\.0, 0\.0\] must be positive pixels"),
        "nan quaternion": (1, r"quaternion/frames\.bin: image 1 \('walk/000\.jpg'\): pose quaternion \(wxyz\) \[nan, "),
        "gps altitude": (1, r"found in 0 of the 15 registered images; 15 more hold altitudes outside Earth's"),
        "export links": (1, rf"{export_dir / 'config.yaml'}: a symbolic link to {victim}, outside the run folder"),
        "sweep, sqlite": (
            1,
            rf"{sqlite_dir / 'optuna.db'}: a symbolic link to {elsewhere / 'x.db'}, outside the sweep",
        ),
        "sweep, journal": (
            1,
            rf"{journal_dir / 'optuna.journal'}: a symbolic link to {elsewhere / 'journal'}, outside",
        ),
    }
    results = run_at_once(commands, tmp_path / "logs")
    for name, (status, pattern) in expected.items():
        code, output, seconds, peak = results[name]
        print(f"{name}: exit status {code}, {seconds:.1f} s of CPU, peak {peak:.0f} MiB of its own")
        assert code == status, f"{name}: exit status {code}\n{output[-3000:]}"
        assert re.search(pattern, output, re.DOTALL), f"{name}: {pattern}\n{output[-3000:]}"
        assert "Traceback" not in output, f"{name}\n{output[-3000:]}"
        assert seconds < WITHIN and 0 < peak < ANONYMOUS_MIB, (name, seconds, peak)
    assert victim.read_text() == "kept\n" and not any(other.iterdir())  # nothing written through the planted links
    assert (
        sorted(path.name for path in elsewhere.iterdir()) == ["journal"]
        and (elsewhere / "journal").read_text() == "kept\n"
    )
