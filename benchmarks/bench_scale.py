"""Time and peak memory of the benchmark core at dataset scale, on generated data.

    .venv/bin/python benchmarks/bench_scale.py [--size baidu|aachen|robotcar] [--dimension 4096] [--keypoints 20000]

``baidu``: Baidu-mall's 689 database images and 2,292 queries, handheld cameras in a
150 m x 60 m mall; ``aachen``: Aachen Day-Night v1.1's 6,697 database images and 1,015 queries,
handheld cameras over a 600 m x 600 m city centre; ``robotcar``: RobotCar Seasons v2's
20,862 x 11,934, left, rear and right cameras of a car every 1.4 m along a 10 km route
(queries: other traversals).
Descriptors vary smoothly with the camera centre and viewing direction (random Fourier
features plus noise), so retrieval finds nearby views. Steps: faiss retrieval, the
relative-pose and frustum ground truths, the co-observation ranking of synthetic
shared-point counts (the SfM behind real ones is not run), the random baseline, paradigm 1
on every ranking, the localization and retrieval metrics. Each step prints its wall time,
the peak of the numpy memory it allocated (tracemalloc) and the process's peak resident
memory so far (ru_maxrss; faiss and BLAS included).

Then the SfM paradigms (2a, 2b) at the published local-feature count (``--keypoints``, 20,000:
the R2D2 features ``r2d2_WASF-N8_20k`` the data configs select): their work counted exactly
(`local_sfm.plan`, `global_sfm.plan`) for these rankings, the k lists of
``configs/paradigms/default.yaml`` and the dataset config's ``sfm.map_pairs``; each stage timed
on a sample at that count (reading an image's published features, matching a pair, a map of
generated points triangulated with known poses, a registration by PnP); and the projected
time of the full sweep on this CPU and with matching on a GPU (measured where there is one;
otherwise ``2 n^2 D / (--gpu-tflops x 10^12)`` per pair, the product at that throughput).
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from omegaconf import OmegaConf

from locretrieval import geometry
from locretrieval.benchmark import relevances
from locretrieval.config import validated
from locretrieval.groundtruth import frustum_groundtruth, groundtruth_from_scores, relative_pose_groundtruth
from locretrieval.localization import approximation, global_sfm, local_sfm
from locretrieval.localization.global_sfm import GlobalSfmSettings
from locretrieval.localization.local_sfm import LocalSfmSettings
from locretrieval.localization.matching import NearestNeighbourMatcher
from locretrieval.localization.sfm import SfmSettings
from locretrieval.localization.pnp import estimate_absolute_pose
from locretrieval.localization.triangulation import triangulate_known_poses
from locretrieval.metrics.localization import localization_table, query_error_table
from locretrieval.metrics.retrieval import retrieval_tables
from locretrieval.retrieval import random_ranking
from locretrieval.retrieval.index import search
from locretrieval.scene import Camera, ImageSet, Scene

CAMERA = Camera("PINHOLE", 1024, 1024, (500.0, 500.0, 512.0, 512.0))
#: (database images, queries) of each dataset
SIZES = {"baidu": (689, 2_292), "aachen": (6_697, 1_015), "robotcar": (20_862, 11_934)}
CONFIGS = Path(__file__).resolve().parents[1] / "configs"
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


def city(count: int, rng: np.random.Generator, prefix: str, size: tuple[float, float] = (600.0, 600.0)) -> ImageSet:
    centers = np.column_stack([rng.uniform(0.0, size[0], count), rng.uniform(0.0, size[1], count), rng.uniform(1.4, 1.8, count)])
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
    parser.add_argument("--keypoints", type=int, default=20_000, help="local features per image (the published R2D2: 20,000)")
    parser.add_argument("--gpu-tflops", type=float, default=50.0, help="GPU float32 throughput of the projection without a GPU")
    args = parser.parse_args()

    rng = np.random.default_rng(args.seed)
    num_database, num_queries = SIZES[args.size]
    started = time.perf_counter()
    if args.size == "baidu":
        database, queries = city(num_database, rng, "db", (150.0, 60.0)), city(num_queries, rng, "query", (150.0, 60.0))
    elif args.size == "aachen":
        database, queries = city(num_database, rng, "db"), city(num_queries, rng, "query")
    else:
        path = road(10_000.0, 1.0, rng)
        database, queries = route(num_database, rng, "db", path, 0.5), route(num_queries, rng, "query", path, 1.5)
    frustum_far = float(OmegaConf.load(CONFIGS / "data" / f"{args.size}.yaml").data.frustum_far)
    scene = Scene(args.size, database, queries, frustum_far=frustum_far)
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
    sfm_at_scale(scene, rankings, args, rng)


def dataset_sfm(size: str) -> SfmSettings:
    """``configs/sfm/default.yaml`` with the dataset config's ``sfm`` section (its ``map_pairs``)."""
    dataset = OmegaConf.load(CONFIGS / "data" / f"{size}.yaml")
    sfm = OmegaConf.merge(OmegaConf.load(CONFIGS / "sfm" / "default.yaml"), {"matching": {"device": "cpu"}}, dataset.sfm)
    return validated(SfmSettings, sfm, "sfm")


def sfm_at_scale(scene: Scene, rankings, args, rng: np.random.Generator) -> None:
    """The SfM paradigms' work for ``rankings`` and its projected time at ``args.keypoints``."""
    sfm = dataset_sfm(args.size)
    paradigms = OmegaConf.load(CONFIGS / "paradigms" / "default.yaml")
    local_settings = LocalSfmSettings(True, list(paradigms.local_sfm.k), str(paradigms.local_sfm.map_matches))
    global_settings = GlobalSfmSettings(True, list(paradigms.global_sfm.k), None)
    with tempfile.TemporaryDirectory(prefix="bench_scale-") as cache:
        work = [
            measure(f"plan: local SfM, k={local_settings.k}", local_sfm.plan, scene, rankings, local_settings, sfm, Path(cache), 0),
            measure(f"plan: global SfM, k={global_settings.k}", global_sfm.plan, scene, rankings, global_settings, sfm, Path(cache), 0),
        ]
    for w in work:
        print(f"  {w.paradigm}: query pairs {w.query_pairs.total:,}, database pairs {w.database_pairs.total:,}, "
              f"maps {w.maps.total:,} (~{w.pairs_per_map:,.0f} pairs each), registrations {w.registrations.total:,}")
    n, processes = args.keypoints, os.cpu_count() or 1
    sample = measure(f"sample at {n:,} keypoints per image", unit_costs, scene, n, sfm, rng)
    pairs = max(w.query_pairs.total for w in work) + sum(w.database_pairs.total for w in work)
    triangulated = sum(w.maps.total * w.pairs_per_map for w in work)
    registrations = sum(w.registrations.total for w in work)
    images = len(scene.database) + len(scene.queries)
    rest = (images * sample["read"] + triangulated * sample["triangulation"] + registrations * sample["registration"]) / processes
    print(f"  per unit: read features {sample['read']:.3f} s/image, match {sample['matching']:.3f} s/pair ({sample['matches']:.0f} "
          f"matches), triangulate {sample['triangulation']:.3f} s/pair ({sample['map_points']:,.0f} points in a 10-image map), "
          f"register {sample['registration']:.3f} s/query ({sample['correspondences']:,.0f} correspondences)")
    gpu = sample.get("gpu_matching", 2 * n * n * 128 / (args.gpu_tflops * 1e12))
    source = "measured" if "gpu_matching" in sample else f"projected at {args.gpu_tflops:g} TFLOP/s"
    for label, per_pair in (("this CPU", sample["matching"]), (f"GPU matching ({source}, {gpu * 1e3:.1f} ms/pair)", gpu)):
        total = pairs * per_pair + rest
        print(f"projected full SfM sweep ({args.size}, {label}, {processes} processes): {total / 3600:.1f} h "
              f"(matching {pairs:,} pairs {pairs * per_pair / 3600:.1f} h, features, maps and registrations {rest / 3600:.1f} h)")


def unit_costs(scene: Scene, count: int, sfm: SfmSettings, rng: np.random.Generator) -> dict[str, float]:
    """Seconds per unit at ``count`` keypoints per image: reading an image's published features
    (float32 R2D2 files), matching a pair (CPU; GPU too where there is one), triangulating a map
    of 10 nearby database images of generated points (per matched pair) and a PnP registration."""
    with tempfile.TemporaryDirectory(prefix="bench_scale-features-") as folder:
        path = Path(folder) / "image.desc"
        rng.normal(size=(count, 128)).astype(np.float32).tofile(path)
        started = time.perf_counter()
        for _ in range(3):
            np.fromfile(path, dtype=np.float32).reshape(count, 128)
        read = (time.perf_counter() - started) / 3
    first = rng.normal(size=(count, 128)).astype(np.float32)
    second = np.concatenate([first[: count // 4] + 0.4 * rng.normal(size=(count // 4, 128)), rng.normal(size=(count - count // 4, 128))])
    matcher = NearestNeighbourMatcher(sfm.matching.ratio)
    matcher(first[:256], [second[:256]])
    started = time.perf_counter()
    matches = matcher(first, [second])[0]
    costs = {"read": read, "matching": time.perf_counter() - started, "matches": len(matches)}
    if torch.cuda.is_available():
        gpu = NearestNeighbourMatcher(sfm.matching.ratio, "cuda")
        gpu(first, [second])
        torch.cuda.synchronize()
        started = time.perf_counter()
        gpu(first, [second])
        torch.cuda.synchronize()
        costs["gpu_matching"] = time.perf_counter() - started
    return costs | generated_map_costs(scene.database, count, sfm, rng)


def generated_map_costs(database: ImageSet, count: int, sfm: SfmSettings, rng: np.random.Generator) -> dict[str, float]:
    """Triangulation per matched pair and PnP per registration on generated geometry: 10 database
    images near the first, 40,000 points in front of them, each image's keypoints the projections
    it sees (filled up to ``count`` with clutter), pairs matched through shared points."""
    near = np.argsort(np.linalg.norm(database.centers - database.centers[0], axis=1))[:10]
    points = database.centers[near].mean(axis=0) + rng.normal(0.0, 15.0, (40_000, 3))
    keypoints, observed = [], []
    for i in near:
        camera_points = geometry.quaternion_to_matrix(database.qvec[i]) @ points.T + database.tvec[i][:, None]
        pixels = 500.0 * camera_points[:2] / camera_points[2] + 512.0
        visible = np.flatnonzero((camera_points[2] > 1.0) & (pixels >= 0).all(0) & (pixels < 1024).all(0))[:count]
        clutter = rng.uniform(0, 1024, (count - len(visible), 2))
        keypoints.append(np.vstack([pixels[:, visible].T + rng.normal(0, 0.5, (len(visible), 2)), clutter]).astype(np.float32))
        observed.append(dict(zip(visible.tolist(), range(len(visible)))))
    matches = {}
    for a in range(len(near)):
        for b in range(a + 1, len(near)):
            shared = observed[a].keys() & observed[b].keys()
            matches[(a, b)] = np.array([[observed[a][p], observed[b][p]] for p in shared], dtype=np.int64).reshape(-1, 2)
    started = time.perf_counter()
    sparse_map = triangulate_known_poses([CAMERA] * len(near), database.qvec[near], database.tvec[near], keypoints, matches, sfm.triangulation)
    triangulation = (time.perf_counter() - started) / len(matches)
    # a registration: the first image's own observations of map points as 2D-3D correspondences, a third of them wrong
    ids = sparse_map.observations[0]
    observed_points = np.flatnonzero(ids >= 0)
    points2D = keypoints[0][observed_points].astype(np.float64)
    points3D = sparse_map.points[ids[observed_points]].copy()
    wrong = rng.random(len(points3D)) < 1 / 3
    points3D[wrong] += rng.normal(0.0, 10.0, (int(wrong.sum()), 3))
    started = time.perf_counter()
    estimate_absolute_pose(points2D, points3D, CAMERA, sfm.pnp)
    registration = time.perf_counter() - started
    return {"triangulation": triangulation, "registration": registration, "map_points": sparse_map.num_points,
            "correspondences": len(points2D)}


if __name__ == "__main__":
    main()
