"""Paradigm 1 speed: 10,000 queries x k = 1..50 x EWB/BDI/CSI, all queries at once.

    .venv/bin/python benchmarks/bench_approximation.py [--queries 10000] [--dimension 4096]
"""

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation

import locretrieval  # noqa: F401
from locretrieval import geometry
from locretrieval.localization.approximation import approximate_poses
from locretrieval.retrieval import Ranking
from locretrieval.scene import Camera, ImageSet


def unit_rows(rng: np.random.Generator, rows: int, dimension: int) -> np.ndarray:
    values = rng.normal(size=(rows, dimension)).astype(np.float32)
    return values / np.linalg.norm(values, axis=1, keepdims=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=10_000)
    parser.add_argument("--database", type=int, default=2_000)
    parser.add_argument("--dimension", type=int, nargs="+", default=[256, 4096])
    parser.add_argument("--depth", type=int, default=50)
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    camera = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
    qvec = Rotation.random(args.database, random_state=0).as_quat()[:, [3, 0, 1, 2]]
    tvec = geometry.translations_from_centers(qvec, rng.uniform(-50, 50, size=(args.database, 3)))
    database = ImageSet([f"db/{i}.jpg" for i in range(args.database)], "/nonexistent", [camera] * args.database, qvec, tvec)
    ks = list(range(1, args.depth + 1))
    for dimension in args.dimension:
        database_descriptors = unit_rows(rng, args.database, dimension)
        query_descriptors = unit_rows(rng, args.queries, dimension)
        indices = np.stack([rng.choice(args.database, args.depth, replace=False) for _ in range(args.queries)])
        scores = np.einsum("qkd,qd->qk", database_descriptors[indices], query_descriptors)
        order = np.argsort(-scores, axis=1)
        ranking = Ranking(
            "bench",
            np.take_along_axis(indices, order, 1),
            np.take_along_axis(scores, order, 1),
            "descriptor",
            query_descriptors,
            database_descriptors,
        )
        for methods in (["ewb"], ["csi"], ["bdi"], ["ewb", "bdi", "csi"]):
            start = time.perf_counter()
            approximate_poses(database, ranking, ks, methods)
            elapsed = time.perf_counter() - start
            print(
                f"paradigm 1: {args.queries} queries x k=1..{args.depth} x {'+'.join(methods):>11}, "
                f"D={dimension}: {elapsed:6.2f} s"
            )


if __name__ == "__main__":
    main()
