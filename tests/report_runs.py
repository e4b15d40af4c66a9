"""A finished evaluate.py run's tables, seeded, for the report tests: rankings, relevance, localization; a
gallery run (`gallery_run`): its images and what galleries read."""

import json
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image
from scipy import sparse

from locretrieval.cache import save_arrays
from locretrieval.metrics.localization import QUERY_ERROR_COLUMNS, QUERY_LOCALIZED_COLUMNS, RESULT_COLUMNS
from locretrieval.metrics.retrieval import retrieval_tables
from locretrieval.metrics.revisited import RevisitedGroundTruth, evaluate_revisited
from locretrieval.metrics.uncertainty import share_interval
from locretrieval.report.gallery import write_gallery_inputs
from locretrieval.retrieval import Ranking
from locretrieval.scene import Camera, ImageSet, Scene

NUM_QUERIES, NUM_DATABASE = 6, 10
KS = [1, 2, 5, 10]
THRESHOLDS = [(0.25, 2.0), (5.0, 10.0)]
GROUNDTRUTH = "gt_relative_pose"
WIDTH, HEIGHT = 40, 30  # pixels of the gallery runs' images (4:3, below any thumbnail size the tests use)


def seeded(name: str) -> np.random.Generator:
    """The same numbers for a ranking in every run (ground truth repeats across a multirun)."""
    return np.random.default_rng(zlib.crc32(name.encode()))


def queries() -> ImageSet:
    camera = Camera("SIMPLE_PINHOLE", 64, 48, (50.0, 32.0, 24.0))
    names = [f"q{i}.png" for i in range(NUM_QUERIES)]
    return ImageSet(
        names, "/x", [camera] * NUM_QUERIES, np.tile([1.0, 0, 0, 0], (NUM_QUERIES, 1)), np.zeros((NUM_QUERIES, 3))
    )


def relevance() -> sparse.csr_matrix:
    return sparse.csr_matrix(seeded("relevance").random((NUM_QUERIES, NUM_DATABASE)) < 0.3)


def ranking(name: str, kind: str) -> Ranking:
    keys = seeded(name).random((NUM_QUERIES, NUM_DATABASE)) - (relevance().toarray() if kind == "groundtruth" else 0)
    return Ranking(name, np.argsort(keys, axis=1), np.zeros((NUM_QUERIES, NUM_DATABASE)), kind)


def localization(name: str, kind: str) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """A ranking's localization tables: ``results.csv``'s rows (with Wilson's intervals), the
    per-query outcomes they count and ``query_errors.csv.gz``'s rows, from seeded errors."""
    rng = seeded(name + "/poses")
    results, outcomes, errors = [], [], []
    paradigms = [("approximation", "ewb"), ("global_sfm", "pnp")]
    paradigms += [("approximation", "csi")] if kind == "descriptor" else []  # CSI needs descriptors
    names = queries().names
    for paradigm, method in paradigms:
        for k in KS:
            position = rng.exponential(1.0, NUM_QUERIES)
            position[rng.random(NUM_QUERIES) < 0.15] = np.nan
            for n, query in enumerate(names):
                failure = "" if np.isfinite(position[n]) else "too few inliers"
                errors.append(
                    ("toy", name, kind, paradigm, method, k, query, position[n], 2 * position[n], failure, "m")
                )
            for x, y in THRESHOLDS:
                hits = np.nan_to_num(position, nan=np.inf) < x
                outcomes += [("toy", name, kind, paradigm, method, k, x, y, q, int(h)) for q, h in zip(names, hits)]
                for subset, members in (("all", slice(None)), ("blurry", slice(0, 3))):
                    count, localized = len(hits[members]), int(hits[members].sum())
                    low, high = share_interval(localized, count, 0.95)
                    row = (paradigm, method, k, min(k, NUM_DATABASE), x, y, 100 * localized / count, count, localized)
                    results.append(("toy", subset, name, kind, *row, 100 * low, 100 * high, "m"))
    return (
        pd.DataFrame(results, columns=RESULT_COLUMNS),
        pd.DataFrame(outcomes, columns=QUERY_LOCALIZED_COLUMNS),
        pd.DataFrame(errors, columns=QUERY_ERROR_COLUMNS),
    )


def write_run(directory: Path, descriptors: list[str]) -> Path:
    """A finished run's tables: the descriptors, the ground truth and a random baseline."""
    directory.mkdir(parents=True)
    rankings = [ranking(name, "descriptor") for name in descriptors]
    rankings += [ranking(GROUNDTRUTH, "groundtruth"), ranking("random", "baseline")]
    subsets = {"all": np.ones(NUM_QUERIES, bool), "blurry": np.arange(NUM_QUERIES) < 3}
    retrieval, per_query = retrieval_tables(
        "toy", rankings, {GROUNDTRUTH: relevance()}, queries(), subsets, range(1, 11), KS
    )
    tables = [localization(r.name, r.kind) for r in rankings]
    pd.concat([t[0] for t in tables]).to_csv(directory / "results.csv", index=False)
    pd.concat([t[1] for t in tables]).to_csv(directory / "query_localized.csv.gz", index=False)
    pd.concat([t[2] for t in tables]).to_csv(directory / "query_errors.csv.gz", index=False)
    retrieval.to_csv(directory / "retrieval.csv", index=False)
    per_query.to_csv(directory / "query_retrieval.csv.gz", index=False)
    pd.DataFrame([{"dataset": "toy", "groundtruth": GROUNDTRUTH, "avg_relevant": 3.1, "missing_pct": 0.0}]).to_csv(
        directory / "groundtruth_statistics.csv", index=False
    )
    pd.DataFrame(
        {
            "dataset": "toy",
            "image": queries().names,
            "blur_score": np.linspace(10, 30, NUM_QUERIES),
            "dynamic_fraction": np.nan,
            "mask_source": "none",
            "blurry": subsets["blurry"],
        }
    ).to_csv(directory / "subsets.csv", index=False)
    revisited = RevisitedGroundTruth([f"db{i}" for i in range(4)], ["q0"], [{"easy": [1], "hard": [2], "junk": [0]}])
    revisited_rankings = [Ranking(name, [[0, 1, 2, 3]], np.zeros((1, 4)), "descriptor") for name in descriptors]
    revisited_tables = [evaluate_revisited(r, revisited, "roxford5k") for r in revisited_rankings]
    pd.concat(revisited_tables).to_csv(directory / "revisited.csv", index=False)
    (directory / "summary.json").write_text(json.dumps({"model": ", ".join(descriptors), "run time": "1.0 s"}))
    return directory


def palette(count: int, offset: int = 0) -> list[tuple[int, int, int]]:
    """``count`` solid colours; the first 16 are at least 73 apart (sum over channels)."""
    return [
        ((37 * i + 50) % 256, (91 * i + 20) % 200 + 30, (151 * i + 90) % 256) for i in range(offset, offset + count)
    ]


def solid_images(folder: Path, colours: list[tuple[int, int, int]], names: list[str]) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for colour, name in zip(colours, names):
        Image.new("RGB", (WIDTH, HEIGHT), colour).save(folder / name)
        paths.append(folder / name)
    return paths


def gallery_run(tmp_path: Path, image_folder: str = "images") -> tuple[Path, list, list]:
    """The toy run of `write_run` at ``tmp_path / "run"``, with solid-colour images (in ``tmp_path / image_folder``)
    and the files galleries read."""
    run = write_run(tmp_path / "run", ["netvlad"])
    database_colours, query_colours = palette(NUM_DATABASE), palette(NUM_QUERIES, offset=NUM_DATABASE)
    solid_images(tmp_path / image_folder, database_colours, [f"db{i}.png" for i in range(NUM_DATABASE)])
    solid_images(tmp_path / image_folder, query_colours, [f"q{i}.png" for i in range(NUM_QUERIES)])
    camera = Camera("SIMPLE_PINHOLE", WIDTH, HEIGHT, (40.0, 20.0, 15.0))

    def images(names: list[str]) -> ImageSet:
        return ImageSet(
            names,
            tmp_path / image_folder,
            [camera] * len(names),
            np.tile([1.0, 0, 0, 0], (len(names), 1)),
            np.zeros((len(names), 3)),
        )

    scene = Scene(
        "toy", images([f"db{i}.png" for i in range(NUM_DATABASE)]), images([f"q{i}.png" for i in range(NUM_QUERIES)])
    )
    write_gallery_inputs(scene, {GROUNDTRUTH: relevance()}, run)
    for name, kind in (("netvlad", "descriptor"), (GROUNDTRUTH, "groundtruth")):
        save_arrays(
            run / "rankings" / f"{name}.npz", {"indices": ranking(name, kind).indices, "kind": np.asarray(kind)}
        )
    return run, database_colours, query_colours
