"""A full sweep on a small kapture folder with precomputed features, cold, as NAVER's tutorial.

    .venv/bin/python benchmarks/bench_kapture_sweep.py [--database 12] [--queries 4]
        [--keypoints 500] [--width 640 --height 480] [--keep DIR]

Renders a synthetic scene of 12 database and 4 query images as kapture folders, stores
precomputed global features (image thumbnails) and local features (pycolmap SIFT capped at
``--keypoints`` per image, written as kapture ``r2d2`` keypoints and descriptors in
``reconstruction/``, as the published R2D2 features are), then times one cold
``evaluate.py`` (empty cache) with every paradigm at k in {1, 2, 3, 4, 5, 10, 20}, as a
subprocess, and prints the time between its log lines: start-up, each stage, the report.
Target (issue #13): <= 15 s cold.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from PIL import Image

REPOSITORY = Path(__file__).resolve().parents[1]
FEATURE_NAME = "r2d2"
K = "[1,2,3,4,5,10,20]"


def render(root: Path, args: argparse.Namespace) -> None:
    from locretrieval.scene.synthetic.dataset import render_synthetic_dataset

    render_synthetic_dataset(
        {
            "width": args.width,
            "height": args.height,
            "num_database": args.database,
            "num_queries": args.queries,
            "length": 20.0,
            "seed": 0,
            "workers": 1,
        },
        root,
    )


def write_features(root: Path, keypoints: int) -> None:
    """Thumbnail global features and SIFT local features in each kapture folder's reconstruction/."""
    from locretrieval.config import validated
    from locretrieval.models import export_global_features
    from locretrieval.scene.kapture_io import load_kapture_scene
    from locretrieval.sfm.features import extract_features
    from locretrieval.sfm.settings import SfmSettings

    defaults = OmegaConf.load(REPOSITORY / "configs" / "sfm" / "default.yaml")
    settings = validated(
        SfmSettings,
        OmegaConf.merge(
            defaults, {"features": {"sift": {"max_num_features": keypoints}}, "matching": {"device": "cpu"}}
        ),
        "sfm",
    )
    scene = load_kapture_scene("sweep", [root / "mapping"], [root / "query"])
    for folder, images in ((root / "mapping", scene.database), (root / "query", scene.queries)):
        thumbnails = np.stack(
            [np.asarray(Image.open(path).convert("L").resize((16, 12)), np.float32).ravel() for path in images.paths]
        )
        thumbnails -= thumbnails.mean(axis=1, keepdims=True)
        export_global_features(
            images.names, thumbnails / np.linalg.norm(thumbnails, axis=1, keepdims=True), folder, "thumbnail"
        )
        local = extract_features(images, settings.features, root / "extraction", workers=1).load(images.names)
        reconstruction = folder / "reconstruction"
        for kind, header in (
            ("keypoints", f"{FEATURE_NAME}, float32, 2"),
            ("descriptors", f"{FEATURE_NAME}, float32, 128, {FEATURE_NAME}, L2"),
        ):
            (reconstruction / kind / FEATURE_NAME).mkdir(parents=True, exist_ok=True)
            (reconstruction / kind / FEATURE_NAME / f"{kind}.txt").write_text(f"# kapture format: 1.1\n{header}\n")
        for name, (points, descriptors) in local.items():
            for kind, array, suffix in (
                ("keypoints", points - 0.5, "kpt"),  # R2D2's pixel centres start at 0
                ("descriptors", descriptors / np.linalg.norm(descriptors, axis=1, keepdims=True), "desc"),
            ):
                path = reconstruction / kind / FEATURE_NAME / f"{name}.{suffix}"
                path.parent.mkdir(parents=True, exist_ok=True)
                np.ascontiguousarray(array, dtype=np.float32).tofile(path)


def stages(log: str, started: float) -> list[tuple[float, str]]:
    """``(seconds since the process started, message)`` of each log line."""
    lines = []
    for match in re.finditer(r"^\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3})\]\[[^\]]+\]\[\w+\] - (.*)$", log, re.M):
        stamp = datetime.strptime(match.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()
        lines.append((stamp - started, match.group(2)[:110]))
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--database", type=int, default=12)
    parser.add_argument("--queries", type=int, default=4)
    parser.add_argument("--keypoints", type=int, default=500)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--keep", type=Path, help="build the folder here and keep it (default: a temporary one)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as folder:
        root = args.keep or Path(folder)
        data = root / "data"
        if not (data / "query").is_dir():
            render(data, args)
            write_features(data, args.keypoints)
        command = [
            sys.executable,
            str(REPOSITORY / "evaluate.py"),
            "data=kapture",
            f"data.root={data}",
            "data.mapping=mapping",
            "data.queries=[query]",
            "model=precomputed",
            "model.feature_name=thumbnail",
            "sfm/features=kapture",
            f"sfm.features.name={FEATURE_NAME}",
            f"paradigms.approximation.k={K}",
            f"paradigms.local_sfm.k={K}",
            f"paradigms.global_sfm.k={K}",
            f"paths.cache_dir={root / 'cache'}",
            f"hydra.run.dir={root / 'run'}",
        ]
        subprocess.run(["rm", "-rf", str(root / "cache"), str(root / "run")], check=True)
        started = time.time()
        result = subprocess.run(command, capture_output=True, text=True, cwd=root)
        seconds = time.time() - started
        if result.returncode:
            sys.exit(f"evaluate.py failed:\n{result.stderr[-3000:]}")
        log = (root / "run" / "evaluate.log").read_text() if (root / "run" / "evaluate.log").exists() else result.stderr
    previous = 0.0
    for offset, message in stages(log, started):
        print(f"{offset:6.2f} s (+{offset - previous:5.2f})  {message}")
        previous = offset
    print(
        f"{args.database} database + {args.queries} query images, {args.keypoints} keypoints, every paradigm at "
        f"k={K}: cold evaluate.py {seconds:.1f} s (last log line at {previous:.1f} s)"
    )


if __name__ == "__main__":
    main()
