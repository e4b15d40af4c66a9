"""Time the ground-truth definitions on a Baidu-mall-sized set of random indoor poses.

    python benchmarks/bench_groundtruth.py [--queries 2300] [--database 700] [--far 50]

Cameras stand on a mall-like floor (``--length`` x ``--width`` metres, 1.2-1.8 m high),
look in a uniformly random horizontal direction with a few degrees of pitch and roll,
and have a 1920x1080 pinhole camera with a ~65 degree horizontal field of view.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from scipy.spatial.transform import Rotation

from locretrieval import geometry
from locretrieval.groundtruth import compute_groundtruths
from locretrieval.scene import Camera, ImageSet, Scene

CAMERA = Camera("PINHOLE", 1920, 1080, (1500.0, 1500.0, 960.0, 540.0))
#: The ground truths' YAMLs: each definition's parameters, the retrieval metrics' relevance.
GROUNDTRUTH = Path(__file__).resolve().parents[1] / "configs" / "groundtruth"


def random_indoor_images(count: int, length: float, width: float, rng: np.random.Generator, prefix: str) -> ImageSet:
    """Images on the floor ``[0, length] x [0, width]`` (world z up), world-to-camera poses."""
    yaw = rng.uniform(0.0, 360.0, count)
    pitch = rng.normal(0.0, 5.0, count)
    roll = rng.normal(0.0, 2.0, count)
    # Camera x right, y down, z forward; at zero angles it looks along world +x.
    level = Rotation.from_matrix([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    camera_to_world = Rotation.from_euler("zyx", np.stack([yaw, pitch, roll], 1), degrees=True) * level
    x, y, z, w = camera_to_world.inv().as_quat().T
    qvec = np.stack([w, x, y, z], 1)
    centers = np.stack(
        [rng.uniform(0.0, length, count), rng.uniform(0.0, width, count), rng.uniform(1.2, 1.8, count)], 1
    )
    tvec = geometry.translations_from_centers(qvec, centers)
    names = [f"{prefix}/{i:05d}.jpg" for i in range(count)]
    return ImageSet(names, "/nonexistent", [CAMERA] * count, qvec, tvec)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--queries", type=int, default=2300)
    parser.add_argument("--database", type=int, default=700)
    parser.add_argument("--length", type=float, default=240.0, help="floor length, metres")
    parser.add_argument("--width", type=float, default=60.0, help="floor width, metres")
    parser.add_argument("--far", type=float, default=50.0, help="frustum far plane, metres")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    rng = np.random.default_rng(args.seed)
    database = random_indoor_images(args.database, args.length, args.width, rng, "db")
    queries = random_indoor_images(args.queries, args.length, args.width, rng, "query")
    scene = Scene("random_indoor", database, queries)
    definitions = {
        name: OmegaConf.load(GROUNDTRUTH / "definitions" / f"{name}.yaml") for name in ("relative_pose", "frustum")
    }
    definitions["frustum"].far = args.far
    relevance = OmegaConf.load(GROUNDTRUTH / "relevance" / "top_k.yaml")
    print(f"{args.queries} queries x {args.database} database images = {args.queries * args.database:,} pairs")
    for name, parameters in definitions.items():
        started = time.perf_counter()
        settings = {"depth": 50, "definitions": {name: parameters}, "enabled": None, "relevance": relevance}
        groundtruth = compute_groundtruths(scene, settings)[name]
        elapsed = time.perf_counter() - started
        statistics = groundtruth.statistics()
        print(
            f"{name:>14}: {elapsed:6.2f} s | avg relevant {statistics['avg_relevant']:.1f} "
            f"(in top 50: {statistics['avg_relevant_in_ranking']:.1f}) | missing {statistics['missing_pct']:.2f} %"
        )


if __name__ == "__main__":
    main()
