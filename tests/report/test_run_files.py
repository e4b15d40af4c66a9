"""A shared run folder stays inside: report.py reads only the runs it is given (their images included,
unless ``--images`` names the dataset's folder), writes only its output, resolves no interpolation
of a run's YAML, reads that YAML within ``limits.yaml_nodes``, and names a damaged table's cell."""

import html
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from report_runs import GROUNDTRUTH, NUM_DATABASE, NUM_QUERIES, gallery_run, write_run

from locretrieval.errors import DataFileError
from locretrieval.report.run_files import load_yaml
from locretrieval.report.tables import load_runs, run_variants

ROOT = Path(__file__).resolve().parents[2]
SECRET = "s3cr3t-in-the-environment"
#: Records every file the report's interpreter opens (Python's audit events), then runs report.py.
AUDITED_REPORT = """import runpy, sys
log = open(sys.argv[1], "w")
sys.addaudithook(lambda event, args: event == "open" and log.write(f"{args[0]}\\t{args[1]}\\n"))
sys.argv = ["report.py", *sys.argv[2:]]
runpy.run_path("report.py", run_name="__main__")
"""


def shared_run(tmp_path: Path) -> tuple[Path, Path]:
    """A run whose files point outside it: images, a cache folder and interpolations of the environment."""
    outside = tmp_path / "outside"
    run, _, _ = gallery_run(tmp_path, image_folder="outside/images")
    gallery = {"queries": "selected", "k": 3, "worst": 2, "random": 1, "seed": 0, "thumbnail_size": 32}
    config = {
        "paths": {"cache_dir": str(outside / "cache")},
        "report": {"gallery": gallery},
        "sfm": {"features": {"_target_": "locretrieval.sfm.features.KaptureFeatures", "name": "${oc.env:SECRET}"}},
    }
    (run / "config.yaml").write_text(yaml.safe_dump(config))
    (run / ".hydra").mkdir()
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(["model.name=${oc.env:SECRET}"]))
    return run, outside


def test_report_py_reads_and_writes_nothing_outside_the_run_and_its_output(tmp_path):
    run, outside = shared_run(tmp_path)
    output, opened = tmp_path / "report", tmp_path / "opened.txt"
    environment = {**os.environ, "PYTHONPATH": str(ROOT), "SECRET": SECRET, "MPLCONFIGDIR": str(tmp_path / "mpl")}
    done = subprocess.run(
        [sys.executable, "-c", AUDITED_REPORT, str(opened), str(run), "--output", str(output), "--formats"],
        cwd=ROOT,
        env=environment,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    files = [line.split("\t") for line in opened.read_text().splitlines()]
    reached = [path for path, _ in files if os.path.realpath(path).startswith(str(outside))]
    assert reached == []  # not an image of images.csv, not the run's paths.cache_dir
    assert not (outside / "cache").exists()
    written = [path for path, mode in files if any(c in mode for c in "wax+") and path.startswith(str(tmp_path))]
    assert written and all(Path(path).is_relative_to(output) or "mpl" in path for path in written), written
    report = (output / "report.md").read_text()
    assert "lie outside the run folder; give the dataset's folder to report.py (`--images DIR`)" in report
    for path in output.rglob("*"):
        assert not path.is_file() or SECRET.encode() not in path.read_bytes(), path
    assert "kapture ${oc.env:SECRET}" in html.unescape(report)  # the published section's local features, as written


def test_a_run_file_linked_outside_the_run_is_refused(tmp_path):
    run = write_run(tmp_path / "run", ["netvlad"])
    secret = tmp_path / "secret.csv"
    secret.write_text("password,hunter2\n")
    (run / "summary.json").unlink()
    (run / "summary.json").symlink_to(secret)
    with pytest.raises(DataFileError, match=rf"summary\.json: resolves to {secret}, outside the run folder"):
        load_runs([run])


def test_a_runs_yaml_is_read_as_written_within_its_budget(tmp_path, monkeypatch):
    runs = [write_run(tmp_path / name, ["netvlad"]) for name in ("a", "b")]
    for run, value in zip(runs, ("${oc.env:HOME}", "${now:%Y}")):
        (run / ".hydra").mkdir()
        (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([f"model.name={value}", "seed=0"]))
    assert list(run_variants(runs).values()) == ["model.name=${oc.env:HOME}", "model.name=${now:%Y}"]
    bomb = tmp_path / "config.yaml"
    levels = ["a: &a [x, x, x, x, x, x, x, x, x, x]"]
    levels += [f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join([f'*{chr(97 + i)}'] * 10)}]" for i in range(8)]
    bomb.write_text("\n".join(levels) + "\n")
    assert bomb.stat().st_size < 500
    with pytest.raises(DataFileError, match=r"config\.yaml: more than 100000 YAML nodes, aliases counted at each use"):
        load_yaml(bomb)
    (tmp_path / "loop.yaml").write_text("a: &a [1, *a]\n")
    with pytest.raises(DataFileError, match=r"loop\.yaml: an alias inside what it names"):
        load_yaml(tmp_path / "loop.yaml")
    assert load_yaml(tmp_path / "a" / ".hydra" / "overrides.yaml") == ["model.name=${oc.env:HOME}", "seed=0"]


def test_report_py_names_a_text_nan_without_a_traceback(tmp_path):
    run = write_run(tmp_path / "run", ["netvlad"])
    results = pd.read_csv(run / "results.csv", dtype=str, keep_default_na=False)
    results.loc[3, "localized_pct"] = "nan"
    results.to_csv(run / "results.csv", index=False)
    done = subprocess.run(
        [sys.executable, "report.py", str(run), "--formats"],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert done.stderr.startswith(f"{run / 'results.csv'}: line 5, column 'localized_pct': 'nan' is not a number")
    assert not (run / "report.md").exists()  # stopped before writing


def test_damaged_gallery_inputs_and_summary_are_named(tmp_path):
    from locretrieval.cache import save_arrays
    from locretrieval.report.gallery import GalleryInputs, relevance_file

    run, _, _ = gallery_run(tmp_path)
    assert GalleryInputs.read(run, GROUNDTRUTH, [tmp_path]).rankings.keys() == {"netvlad"}
    ranking = run / "rankings" / "netvlad.npz"
    save_arrays(ranking, {"indices": np.full((NUM_QUERIES, 3), NUM_DATABASE), "kind": np.asarray("descriptor")})
    with pytest.raises(DataFileError, match=rf"netvlad\.npz: indices int64 \({NUM_QUERIES}, 3\) are not a ranking"):
        GalleryInputs.read(run, GROUNDTRUTH, [tmp_path])
    save_arrays(ranking, {"indices": np.zeros((NUM_QUERIES, 3), dtype=np.int64), "kind": np.asarray("descriptor")})
    save_arrays(relevance_file(run, GROUNDTRUTH), {"indptr": [0, 1], "indices": [0], "shape": [1, 1]})
    with pytest.raises(DataFileError, match=r"a relevance matrix of shape \(1, 1\), not \(6, 10\) as images\.csv"):
        GalleryInputs.read(run, GROUNDTRUTH, [tmp_path])
    (run / "summary.json").write_text("[1, 2]")
    with pytest.raises(DataFileError, match=r"summary\.json: not a JSON object of labels and values"):
        load_runs([run])
