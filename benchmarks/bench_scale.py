"""Time and peak memory of the benchmark core at dataset scale, on generated data.

    .venv/bin/python benchmarks/bench_scale.py [--size aachen|robotcar] [--dimension 4096]

``aachen``: Aachen Day-Night v1.1's 6,697 database images and 1,015 queries, handheld cameras
over a 600 m x 600 m city centre; ``robotcar``: RobotCar Seasons v2's 20,862 x 11,934, left,
rear and right cameras of a car every 1.4 m along a 10 km route (queries: other traversals).
Descriptors vary smoothly with the camera centre and viewing direction (random Fourier
features plus noise), so retrieval finds nearby views. Steps: faiss retrieval, the
relative-pose and frustum ground truths, the co-observation ranking of synthetic
shared-point counts (the SfM behind real ones is not run), the random baseline, paradigm 1
on every ranking, the localization and retrieval metrics. Each step prints its wall time,
the peak of the numpy memory it allocated (tracemalloc) and the process's peak resident
memory so far (ru_maxrss; faiss and BLAS included).
"""

from __future__ import annotations

import argparse
import resource
import time
import tracemalloc

import numpy as np
from scipy.spatial.transform import Rotation

from locretrieval import geometry
from locretrieval.benchmark import relevances
from locretrieval.groundtruth import frustum_groundtruth, groundtruth_from_scores, relative_pose_groundtruth
from locretrieval.localization import approximation
from locretrieval.metrics.localization import localization_table, query_error_table
from locretrieval.metrics.retrieval import retrieval_tables
from locretrieval.retrieval import random_ranking
from locretrieval.retrieval.index import search
from locretrieval.scene import Camera, ImageSet, Scene

CAMERA = Camera("PINHOLE", 1024, 1024, (500.0, 500.0, 512.0, 512.0))
#: (database images, queries) of each dataset
SIZES = {"aachen": (6_697, 1_015), "robotcar": (20_862, 11_934)}
DEPTH = 50
KS = [1, 2, 3, 5, 10, 20, 50]  # configs/paradigms/default.yaml, approximation
THRESHOLDS = [[0.25, 2.0], [0.5, 5.0], [5.0, 10.0]]  # configs/evaluate.yaml
GIB = 2.0**30


def images(centers: np.ndarray, yaw: np.ndarray, rng: np.random.Generator, prefix: str) -> ImageSet:
    """Level-ish cameras at ``centers`` looking along world heading ``yaw`` (degrees, z up)."""
    pitch, roll = rng.normal(0.0, 3.0, len(yaw)), rng.normal(0.0, 1.0, len(yaw))
    level = Rotation.from_matrix([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera z along world x
    camera_to_world = Rotation.from_euler("zyx", np.stack([yaw, pitch, roll], 1), degrees=True) * level
    x, y, z, w = camera_to_world.inv().as_quat().T
    qvec = np.stack([w, x, y, z], 1)
    names = [f"{prefix}/{i:05d}.jpg" for i in range(len(yaw))]
    return ImageSet(names, "/nonexistent", [CAMERA] * len(yaw), qvec, geometry.translations_from_centers(qvec, centers))


def city(count: int, rng: np.random.Generator, prefix: str) -> ImageSet:
    centers = np.column_stack([rng.uniform(0.0, 600.0, (count, 2)), rng.uniform(1.4, 1.8, count)])
    return images(centers, rng.uniform(0.0, 360.0, count), rng, prefix)


def route(count: int, rng: np.random.Generator, prefix: str, path: tuple[np.ndarray, np.ndarray], spread: float) -> ImageSet:
    """``count`` images, 3 per car position (left, rear, right) at random points of ``path``
    (points, headings) moved sideways by ``spread`` metres (standard deviation)."""
    points, headings = path
    at = np.sort(rng.integers(0, len(points), count // 3 + 1))
    heading = headings[at] + rng.normal(0.0, 3.0, len(at))
    side = np.radians(heading + 90.0)
    sideways = np.column_stack([np.cos(side), np.sin(side), np.zeros(len(at))])
    centers = points[at] + rng.normal(0.0, spread, (len(at), 1)) * sideways
    yaw = (heading[:, None] + [90.0, 180.0, -90.0]).ravel()[:count]
    return images(np.repeat(centers, 3, axis=0)[:count], yaw, rng, prefix)


def road(length: float, step: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random road: points every ``step`` metres (1.5 m high) and their headings (degrees)."""
    turns = np.convolve(rng.normal(0.0, 2.0, int(length / step)), np.ones(25) / 5.0, mode="same")
    heading = np.cumsum(turns)
    direction = np.radians(heading)
    xy = np.cumsum(step * np.column_stack([np.cos(direction), np.sin(direction)]), axis=0)
    return np.column_stack([xy, np.full(len(xy), 1.5)]), heading


def descriptors(image_set: ImageSet, projection: np.ndarray, phase: np.ndarray, noise: float, rng: np.random.Generator) -> np.ndarray:
    """L2-normalised float32 ``[n, D]``: random Fourier features of (centre / 15 m, viewing
    direction / 0.5) plus Gaussian noise, in chunks of images."""
    viewing = geometry.quaternion_to_matrix(image_set.qvec)[:, 2]  # camera z-axis in world coordinates
    inputs = np.column_stack([image_set.centers / 15.0, viewing / 0.5])
    out = np.empty((len(image_set), projection.shape[0]), dtype=np.float32)
    for start in range(0, len(image_set), 2048):
        rows = slice(start, start + 2048)
        values = np.cos(inputs[rows] @ projection.T + phase) + noise * rng.normal(size=(len(inputs[rows]), len(phase)))
        out[rows] = values / np.linalg.norm(values, axis=1, keepdims=True)
    return out


def synthetic_co_observation(database: ImageSet, queries: ImageSet, overlapping, rng: np.random.Generator):
    """The co-observation ranking (its `co_observation_groundtruth` scoring) of random
    shared-point counts between frustum-overlapping pairs."""
    shared = overlapping.astype(np.float64)
    shared.data = rng.integers(1, 500, shared.nnz).astype(np.float64)

    def score_block(rows: np.ndarray):
        counts = shared[rows].toarray()
        return counts, counts > 0, counts >= 1

    return groundtruth_from_scores("gt_co_observation", database, queries, DEPTH, score_block)


def measure(label: str, function, *args, **kwargs):
    """``function(*args, **kwargs)``, printing its time and memory."""
    tracemalloc.reset_peak()
    before = tracemalloc.get_traced_memory()[0]
    started = time.perf_counter()
    result = function(*args, **kwargs)
    elapsed = time.perf_counter() - started
    peak = tracemalloc.get_traced_memory()[1] - before
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / GIB
    print(f"{label:<44} {elapsed:8.2f} s | step peak {peak / GIB:6.2f} GiB | process peak RSS {rss:6.2f} GiB", flush=True)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", choices=sorted(SIZES), default="aachen")
    parser.add_argument("--dimension", type=int, default=4096)
    parser.add_argument("--noise", type=float, default=0.5, help="descriptor noise (relative to the features)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    rng = np.random.default_rng(args.seed)
    num_database, num_queries = SIZES[args.size]
    started = time.perf_counter()
    if args.size == "aachen":
        database, queries = city(num_database, rng, "db"), city(num_queries, rng, "query")
    else:
        path = road(10_000.0, 1.0, rng)
        database, queries = route(num_database, rng, "db", path, 0.5), route(num_queries, rng, "query", path, 1.5)
    scene = Scene(args.size, database, queries)
    projection, phase = rng.normal(size=(args.dimension, 6)), rng.uniform(0.0, 2 * np.pi, args.dimension)
    database_descriptors = descriptors(database, projection, phase, args.noise, rng)
    query_descriptors = descriptors(queries, projection, phase, args.noise, rng)
    print(
        f"{args.size}: {num_database:,} database images x {num_queries:,} queries, D={args.dimension} "
        f"(generated in {time.perf_counter() - started:.1f} s)"
    )

    tracemalloc.start()
    ranking = measure("retrieval (faiss, top 50)", search, query_descriptors, database_descriptors, DEPTH)
    groundtruths = {
        "relative_pose": measure(
            "ground truth: relative pose (25 m, 45 deg)", relative_pose_groundtruth, database, queries,
            depth=DEPTH, position_threshold=25.0, rotation_threshold=45.0,
        ),
        "frustum": measure(
            "ground truth: frustum (0.1-50 m)", frustum_groundtruth, database, queries,
            depth=DEPTH, near=0.1, far=50.0, min_radius=0.0,
        ),
    }
    groundtruths["co_observation"] = measure(
        "ground truth: co-observation (synthetic)", synthetic_co_observation,
        database, queries, groundtruths["frustum"].relevance, rng,
    )
    baseline = measure("random baseline ranking", random_ranking, num_queries, num_database, DEPTH, args.seed)
    settings = approximation.ApproximationSettings(enabled=True, k=KS, methods=list(approximation.METHODS), alpha=8.0)
    estimates = measure("paradigm 1: descriptor (ewb, bdi, csi)", approximation.run, scene, [ranking], settings)
    rankings = [ranking, *(gt.ranking for gt in groundtruths.values()), baseline]
    estimates += measure("paradigm 1: ground truths + random (ewb)", approximation.run, scene, rankings[1:], settings)
    subsets = {"all": np.ones(num_queries, dtype=bool)}
    measure(
        "localization metrics (tables)",
        lambda: (localization_table(args.size, estimates, queries, THRESHOLDS, subsets), query_error_table(args.size, estimates, queries)),
    )
    relevance = measure("relevance in the top 50", relevances, groundtruths)
    tables = measure("retrieval metrics (P/R/mAP@1..50)", retrieval_tables, args.size, rankings, relevance, queries, subsets, range(1, DEPTH + 1), KS)
    recall = tables[0].query("ranking == 'descriptor' and groundtruth == 'relative_pose' and metric == 'recall'")
    localized = [e for e in estimates if e.ranking == "descriptor" and e.method == "bdi"][0]
    errors = localized.errors(queries.qvec, queries.tvec)[0][KS.index(10)]
    print(f"sanity: descriptor R@1 {recall['value'].iloc[0]:.2f}, R@50 {recall['value'].iloc[-1]:.2f} (relative pose); "
          f"bdi k=10 median position error {np.nanmedian(errors):.1f} m")


if __name__ == "__main__":
    main()
