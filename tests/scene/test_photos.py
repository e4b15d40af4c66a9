"""``data=photos``: photos of a walk through the synthetic mall, rendered without their poses (GPS in
their EXIF), reconstructed by pycolmap and benchmarked, beside the same benchmark on the true poses;
the reconstruction cached and resumed; bad photo folders refused before any reconstruction."""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import pandas as pd
import pytest
from helpers import evaluate, evaluate_config
from own_place import render_walk, write_truth_kapture
from PIL import Image

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.build import scene_of
from locretrieval.errors import DataFileError
from locretrieval.scene import photos
from locretrieval.scene.datasets import DatasetNotFoundError

#: 20 photos 0.53 m apart along 10 m, 320 x 240 at 70 degrees; every 5th is a query (data.split's default).
PHOTOS, WIDTH, HEIGHT, LENGTH = 20, 320, 240, 10.0
QUERIES = list(range(0, PHOTOS, 5))
#: SIFT on small photos: every octave, at most 2048 features.
RECONSTRUCTION = ("data.reconstruction.first_octave=0", "data.reconstruction.max_num_features=2048")
#: The same small benchmark on both scenes: every paradigm on the model's ranking.
BENCHMARK = (
    "device=cpu", "model.max_side=160", "model.step=4", "groundtruth=none", "baselines.random=false",
    "paradigms.approximation.k=[1,3]", "paradigms.local_sfm.k=[3]", "paradigms.global_sfm.k=[3]",
    "sfm.features.max_num_features=1024", "sfm.map_pairs.max_per_image=6", "subsets.dynamic_masks=[]",
    "subsets.blur_width=160", "report.figure_formats=[]", "report.scene_view.enabled=false", "output.ltvl=false",
)  # fmt: skip


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    return render_walk(
        tmp_path_factory.mktemp("photos_walk") / "photos", PHOTOS, WIDTH, HEIGHT, gps=True, length=LENGTH
    )


@pytest.mark.slow
def test_photos_reconstruct_near_the_true_poses_and_benchmark_as_the_true_poses_do(tmp_path, walk, monkeypatch, caplog):
    paths = (f"data.images={walk.folder}", f"paths.root_dir={tmp_path}")
    cfg = evaluate_config("data=photos", *paths, *RECONSTRUCTION, *BENCHMARK)

    def interrupted(*arguments):
        raise KeyboardInterrupt

    monkeypatch.setattr(photos, "build_models", interrupted)  # killed after features and matches
    with pytest.raises(KeyboardInterrupt):
        scene_of(cfg.data)
    monkeypatch.undo()
    with caplog.at_level(logging.INFO):
        evaluate(cfg, tmp_path / "photos_run")  # the documented command: resumes the reconstruction, benchmarks it
        scene = scene_of(cfg.data)
    assert "reconstruction of" in caplog.text and "cached in" in caplog.text  # the second load reconstructs nothing

    # the camera centres, after a similarity alignment to the true ones: the shops across the corridor are
    # ~7 m away, where a pixel spans 7 m / 228 px = 3 cm; the photos are 0.53 m apart. The median camera
    # within 0.1 m (3 pixels' span), every one within 0.25 m (half the step between photos).
    import pycolmap

    names = [*scene.database.names, *scene.queries.names]
    assert sorted(names) == walk.names  # every photo registered
    centres = np.concatenate([scene.database.centers, scene.queries.centers])
    truth = walk.centres[[walk.names.index(name) for name in names]]
    aligned = np.asarray(pycolmap.estimate_sim3d(centres, truth).matrix())
    errors = np.linalg.norm(centres @ aligned[:, :3].T + aligned[:, 3] - truth, axis=1)
    assert np.median(errors) < 0.1 and errors.max() < 0.25, errors
    quality = json.loads((tmp_path / "photos_run" / "summary.json").read_text())["pseudo ground truth"]
    assert quality["registered images"] == "20 of 20 (100.0 %)" and quality["scale"].startswith("GPS of 20 images")
    assert quality["GPS residual median (m)"] == pytest.approx(np.median(errors), abs=0.02)  # GPS = the true centres
    report = (tmp_path / "photos_run" / "report.md").read_text()
    assert "**pseudo ground truth**: model: " in report and "registered images: 20 of 20" in report

    # the benchmark on the true poses (kapture folders, the same photos and split): every paradigm's
    # results agree within one query (25 points of 4 queries; measured: equal)
    folders = write_truth_kapture(
        walk, tmp_path / "truth", {"mapping": [i for i in range(PHOTOS) if i not in QUERIES], "query": QUERIES}
    )
    kapture = (f"data.mapping={folders['mapping']}", f"data.queries=[{folders['query']}]")
    truth_cfg = evaluate_config("data=kapture", *kapture, f"paths.root_dir={tmp_path}", *BENCHMARK)
    evaluate(truth_cfg, tmp_path / "truth_run")
    keys = ["ranking", "paradigm", "method", "k", "position_threshold_m", "rotation_threshold_deg", "subset"]
    results = [pd.read_csv(tmp_path / run / "results.csv") for run in ("photos_run", "truth_run")]
    both = results[0].merge(results[1], on=keys, suffixes=("_photos", "_truth"))
    assert set(both["paradigm"]) == {"approximation", "local_sfm", "global_sfm"}
    assert len(both) == len(results[0]) == len(results[1])
    difference = (both["localized_pct_photos"] - both["localized_pct_truth"]).abs()
    assert (difference <= 100 / len(QUERIES)).all(), both[difference > 0]


def test_bad_photo_folders_are_refused_before_any_reconstruction(tmp_path, walk):
    def load(folder, *overrides):
        paths = (f"data.images={folder}", f"paths.root_dir={tmp_path}")
        cfg = evaluate_config("data=photos", *paths, "data.metres_per_unit=1", *overrides)
        return scene_of(cfg.data)

    with pytest.raises(DatasetNotFoundError, match="photo folder not found"):
        load(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no photos here")
    with pytest.raises(DataFileError, match=r"empty: no image files"):
        load(tmp_path / "empty")
    broken = tmp_path / "broken"
    shutil.copytree(walk.folder, broken)
    (broken / "walk" / "005.jpg").write_bytes(b"not a JPEG")
    with pytest.raises(DataFileError, match=r"walk/005.jpg: not a readable image"):
        load(broken)
    copied = tmp_path / "copied"
    shutil.copytree(walk.folder, copied)
    shutil.copy(copied / "walk" / "003.jpg", copied / "walk" / "003 copy.jpg")
    with pytest.raises(DataFileError, match=r"image names with whitespace"):
        load(copied)
    (copied / "walk" / "003 copy.jpg").rename(copied / "walk" / "003_copy.jpg")
    with pytest.raises(DataFileError, match=r"walk/003_copy.jpg: the same image as .*walk/003.jpg"):
        load(copied)
    assert not (tmp_path / ".cache" / "photos").exists()  # nothing was reconstructed


def test_photos_that_do_not_overlap_stop_saying_how_many_registered(tmp_path):
    noise = tmp_path / "noise"
    noise.mkdir()
    rng = np.random.default_rng(0)
    for index in range(6):
        Image.fromarray(rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)).save(noise / f"{index}.png")
    cfg = evaluate_config("data=photos", f"data.images={noise}", f"paths.root_dir={tmp_path}", "data.metres_per_unit=1")
    with pytest.raises(ValueError, match=r"pycolmap registered 0 of the 6 images of .*noise .*too few overlapping"):
        scene_of(cfg.data)
