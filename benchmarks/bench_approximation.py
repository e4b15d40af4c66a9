"""Paradigm 1 speed: 10,000 queries x k = 1..50 x EWB/BDI/CSI.

    .venv/bin/python benchmarks/bench_approximation.py [--queries 10000] [--dimension 4096]

Random unit descriptors and random rotations (the worst case for the rotation averages, whose
4x4 eigenvectors then need LAPACK). Also prints how far BDI's weights, from float32 descriptor
products, are from the float64 solution on the first `--check` queries.
"""

import argparse
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from scipy.spatial.transform import Rotation

import locretrieval  # noqa: F401
from locretrieval import geometry
from locretrieval.paradigms import approximation
from locretrieval.paradigms.approximation import (
    BarycentricWeights,
    CosineSimilarityWeights,
    EqualWeights,
    approximate_poses,
)
from locretrieval.retrieval import Ranking
from locretrieval.scene import Camera, ImageSet

CSI = Path(__file__).resolve().parents[1] / "configs" / "paradigms" / "approximation" / "weights" / "csi.yaml"


def unit_rows(rng: np.random.Generator, rows: int, dimension: int) -> np.ndarray:
    values = rng.normal(size=(rows, dimension)).astype(np.float32)
    return values / np.linalg.norm(values, axis=1, keepdims=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queries", type=int, default=10_000)
    parser.add_argument("--database", type=int, default=2_000)
    parser.add_argument("--dimension", type=int, nargs="+", default=[256, 4096])
    parser.add_argument("--depth", type=int, default=50)
    parser.add_argument("--check", type=int, default=500, help="queries whose BDI weights are compared with float64")
    parser.add_argument("--alpha", type=float, default=OmegaConf.load(CSI).alpha, help="CSI exponent")
    args = parser.parse_args()

    rng = np.random.default_rng(0)
    camera = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))
    qvec = Rotation.random(args.database, random_state=0).as_quat()[:, [3, 0, 1, 2]]
    tvec = geometry.translations_from_centers(qvec, rng.uniform(-50, 50, size=(args.database, 3)))
    database = ImageSet(
        [f"db/{i}.jpg" for i in range(args.database)], "/nonexistent", [camera] * args.database, qvec, tvec
    )
    ks = list(range(1, args.depth + 1))
    built = {"ewb": EqualWeights(), "bdi": BarycentricWeights(), "csi": CosineSimilarityWeights(args.alpha)}
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
            approximate_poses(database, ranking, ks, {name: built[name] for name in methods})
            elapsed = time.perf_counter() - start
            print(
                f"paradigm 1: {args.queries} queries x k=1..{args.depth} x {'+'.join(methods):>11}, "
                f"D={dimension}: {elapsed:6.2f} s"
            )
        print(
            f"BDI weights, float32 products vs float64, first {args.check} queries, D={dimension}: "
            f"max difference {bdi_weight_difference(ranking, ks, args.check):.1e}"
        )


def bdi_weights(ranking: Ranking, ks: list[int], rows: slice) -> np.ndarray:
    """BDI weights ``[len(ks), q, K]`` of the queries ``rows`` as paradigm 1 computes them."""
    factors = approximation._residual_gram_factors(ranking, rows, approximation.DescriptorProducts(ranking))
    return approximation._bdi_weights(factors, ranking.indices[rows] != -1, ks)


def bdi_weight_difference(ranking: Ranking, ks: list[int], count: int) -> float:
    rows = slice(0, count)
    fast = bdi_weights(ranking, ks, rows)
    previous = approximation.EXACT_GRAM_PIVOT
    approximation.EXACT_GRAM_PIVOT = np.inf  # every Gram matrix from float64 residuals
    try:
        exact = bdi_weights(ranking, ks, rows)
    finally:
        approximation.EXACT_GRAM_PIVOT = previous
    return float(np.abs(fast - exact).max())


if __name__ == "__main__":
    main()
