"""Time and peak memory of the benchmark core at dataset scale, on generated data; the SfM sweep projected and checked.

    .venv/bin/python benchmarks/bench_scale.py [--size baidu aachen robotcar] [--dimension 4096] [--keypoints 20000]
                                               [--slice 0.02] [--slice-keypoints 20000] [--scale 1]

``baidu``: Baidu-mall's 689 database images and 2,292 queries, handheld cameras in a
150 m x 60 m mall; ``aachen``: Aachen Day-Night v1.1's 6,697 database images and 1,015 queries,
handheld cameras over a 600 m x 600 m city centre; ``robotcar``: RobotCar Seasons v2's
20,862 x 11,934, left, rear and right cameras of a car every 1.4 m along a 10 km route
(queries: other traversals). ``--scale s`` below 1 generates that share of the images over that
share of the area (the route's length), so the density of the cameras stays the dataset's: the same
steps at a rehearsal's size (`benchmarks/gpu_check.sh --rehearse`).
Descriptors vary smoothly with the camera centre and viewing direction (random Fourier
features plus noise), so retrieval finds nearby views. Steps: faiss retrieval, the
relative-pose and frustum ground truths, the co-observation ranking of synthetic
shared-point counts (the SfM behind real ones is not run), the random baseline, paradigm 1
on every ranking, the localization and retrieval metrics. Each step prints its wall time,
the peak of the numpy memory it allocated (tracemalloc) and the process's peak resident
memory so far (ru_maxrss; faiss and BLAS included).

Then the SfM paradigms (2a, 2b) with the dataset config's settings (``sfm``, from
``python evaluate.py data=<size>``) at the published local-feature count (``--keypoints``,
20,000: the R2D2 features the data configs select), on the device a run would use:

1. their work counted exactly (`count_work`) for these rankings and the k lists of
   ``configs/paradigms/<name>.yaml``;
2. unit costs measured by the dry run's own `calibrate` (the SfM pipeline run on a neighbourhood
   of database images and a few queries) with the features of a generated world
   (`sfm_world.FeatureWorld`: points with descriptors, each image's features their projections
   plus clutter, written as R2D2 kapture files and read back);
3. the full sweep's forecast (`locretrieval.paradigms.forecast.forecast`, what ``dry_run=true`` logs) per stage;
4. **the forecast checked**: a slice of the work (the ``--slice`` share of the queries with the
   smallest x and the database images within 25 m of them, their own rankings, features of
   the generated world at ``--slice-keypoints``) forecast the same way, then run end to end
   through the SfM pipeline (`run_sfm`, both paradigms) and timed against the band the forecast claims.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import resource
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf
from scipy.spatial.transform import Rotation
from sfm_world import FeatureWorld

from locretrieval import geometry
from locretrieval.benchmark import relevances
from locretrieval.config import validated
from locretrieval.groundtruth import frustum_groundtruth, groundtruth_from_scores, relative_pose_groundtruth
from locretrieval.metrics.localization import localization_tables, query_error_table
from locretrieval.metrics.retrieval import retrieval_tables
from locretrieval.metrics.uncertainty import default_uncertainty
from locretrieval.paradigms.approximation import PoseApproximation
from locretrieval.paradigms.base import Paradigms
from locretrieval.paradigms.forecast import BAND, Calibration, calibrate, calibration_sample, forecast
from locretrieval.paradigms.sfm import SfmParadigm, count_work, run_sfm
from locretrieval.retrieval import random_ranking
from locretrieval.retrieval.index import search
from locretrieval.scene import Camera, ImageSet, Scene
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.settings import SfmSettings
from locretrieval.sfm.triangulation import BatchedTriangulation, MapInput
from locretrieval.sfm.work import SfmPlan

CAMERA = Camera("PINHOLE", 1024, 1024, (500.0, 500.0, 512.0, 512.0))
#: (database images, queries) of each dataset
SIZES = {"baidu": (689, 2_292), "aachen": (6_697, 1_015), "robotcar": (20_862, 11_934)}
CONFIGS = Path(__file__).resolve().parents[1] / "configs"
DEPTH = 50
KS = [1, 2, 3, 5, 10, 20, 50]  # configs/paradigms/approximation.yaml
THRESHOLDS = [[0.25, 2.0], [0.5, 5.0], [5.0, 10.0]]  # configs/metrics/default.yaml (inclusive: <=)
GIB = 2.0**30
#: Database images of the map the triangulations are compared on.
TRIANGULATION_IMAGES = 10


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
    centers = np.column_stack(
        [rng.uniform(0.0, size[0], count), rng.uniform(0.0, size[1], count), rng.uniform(1.4, 1.8, count)]
    )
    return images(centers, rng.uniform(0.0, 360.0, count), rng, prefix)


def route(
    count: int, rng: np.random.Generator, prefix: str, path: tuple[np.ndarray, np.ndarray], spread: float
) -> ImageSet:
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


def descriptors(
    image_set: ImageSet, projection: np.ndarray, phase: np.ndarray, noise: float, rng: np.random.Generator
) -> np.ndarray:
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
    print(
        f"{label:<44} {elapsed:8.2f} s | step peak {peak / GIB:6.2f} GiB | process peak RSS {rss:6.2f} GiB", flush=True
    )
    return result


def scene_rankings(
    scene: Scene,
    database_descriptors: np.ndarray,
    query_descriptors: np.ndarray,
    rng: np.random.Generator,
    seed: int,
    timed=lambda label, function, *args, **kwargs: function(*args, **kwargs),
) -> tuple[list, dict]:
    """The five rankings of a run (faiss on the descriptors, the relative-pose, frustum and
    synthetic co-observation ground truths, random) and the ground truths; ``timed(label, f, ...)`` calls each step."""
    database, queries = scene.database, scene.queries
    chunk_size = OmegaConf.load(CONFIGS / "retrieval" / "default.yaml").chunk_size  # evaluate.py's
    ranking = timed(
        "retrieval (faiss, top 50)", search, query_descriptors, database_descriptors, DEPTH, "descriptor", chunk_size
    )
    groundtruths = {
        "relative_pose": timed(
            "ground truth: relative pose (25 m, 45 deg)",
            relative_pose_groundtruth,
            database,
            queries,
            depth=DEPTH,
            position_threshold=25.0,
            rotation_threshold=45.0,
            ranked="within_thresholds",
        ),
        "frustum": timed(
            "ground truth: frustum (0.1-50 m)",
            frustum_groundtruth,
            database,
            queries,
            depth=DEPTH,
            near=0.1,
            far=50.0,
            min_radius=0.0,
        ),
    }
    groundtruths["co_observation"] = timed(
        "ground truth: co-observation (synthetic)",
        synthetic_co_observation,
        database,
        queries,
        groundtruths["frustum"].relevance,
        rng,
    )
    baseline = timed("random baseline ranking", random_ranking, len(queries), len(database), DEPTH, seed)
    return [ranking, *(gt.ranking for gt in groundtruths.values()), baseline], groundtruths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", choices=sorted(SIZES), nargs="+", default=["aachen"])
    parser.add_argument("--dimension", type=int, default=4096)
    parser.add_argument(
        "--scale",
        type=float,
        default=1.0,
        help="share of the dataset's images (and of its area) generated; 1: the published size",
    )
    parser.add_argument("--noise", type=float, default=0.5, help="descriptor noise (relative to the features)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--keypoints", type=int, default=20_000, help="local features per image (the published R2D2: 20,000)"
    )
    parser.add_argument(
        "--slice",
        type=float,
        default=None,
        help="share of the queries in the checked slice (default: 0.02 on a GPU, 0.005 on a CPU)",
    )
    parser.add_argument(
        "--slice-keypoints",
        type=int,
        default=None,
        help="keypoints per image in the slice (default: --keypoints on a GPU, 1,000 on a CPU)",
    )
    args = parser.parse_args()
    if not 0.0 < args.scale <= 1.0:
        parser.error(f"--scale must be in (0, 1], got {args.scale}")
    device = torch.cuda.get_device_name() if torch.cuda.is_available() else f"CPU ({os.cpu_count()} cores)"
    print(f"device: {device}, torch {torch.__version__}")
    for size in args.size:
        run_size(argparse.Namespace(**{**vars(args), "size": size}))


def run_size(args: argparse.Namespace) -> None:
    """Every step at ``args.size``, then the SfM paradigms (`sfm_at_scale`)."""
    rng = np.random.default_rng(args.seed)
    num_database, num_queries = (max(2, round(args.scale * count)) for count in SIZES[args.size])
    side = np.sqrt(args.scale)  # an area of args.scale times the dataset's: the same density of cameras
    started = time.perf_counter()
    if args.size == "baidu":
        mall = (150.0 * side, 60.0 * side)
        database, queries = city(num_database, rng, "db", mall), city(num_queries, rng, "query", mall)
    elif args.size == "aachen":
        centre = (600.0 * side, 600.0 * side)
        database, queries = city(num_database, rng, "db", centre), city(num_queries, rng, "query", centre)
    else:
        path = road(10_000.0 * args.scale, 1.0, rng)
        database, queries = route(num_database, rng, "db", path, 0.5), route(num_queries, rng, "query", path, 1.5)
    frustum_far = float(OmegaConf.load(CONFIGS / "data" / f"{args.size}.yaml").data.frustum_far)
    scene = Scene(args.size, database, queries, frustum_far=frustum_far)
    projection, phase = rng.normal(size=(args.dimension, 6)), rng.uniform(0.0, 2 * np.pi, args.dimension)
    database_descriptors = descriptors(database, projection, phase, args.noise, rng)
    query_descriptors = descriptors(queries, projection, phase, args.noise, rng)
    print(
        f"{args.size}{f' at scale {args.scale:g}' if args.scale < 1 else ''}: "
        f"{num_database:,} database images x {num_queries:,} queries, D={args.dimension} "
        f"(generated in {time.perf_counter() - started:.1f} s)"
    )

    tracemalloc.start()
    rankings, groundtruths = scene_rankings(scene, database_descriptors, query_descriptors, rng, args.seed, measure)
    approximation = approximation_paradigm()
    estimates = measure("paradigm 1: descriptor (ewb, bdi, csi)", approximation.run, scene, rankings[:1], None, None)
    estimates += measure("paradigm 1: ground truths + random (ewb)", approximation.run, scene, rankings[1:], None, None)
    subsets = {"all": np.ones(num_queries, dtype=bool)}
    measure(
        "localization metrics (tables)",
        lambda: (
            localization_tables(
                args.size, estimates, queries, THRESHOLDS, subsets, True, default_uncertainty().confidence
            ),
            query_error_table(args.size, estimates, queries),
        ),
    )
    scope = instantiate(evaluate_config([]).groundtruth.relevance)  # evaluate.py's: the top-50 ranking's
    relevance = measure("relevance in the top 50", relevances, groundtruths, scope)
    tables = measure(
        "retrieval metrics (P/R/mAP@1..50)",
        retrieval_tables,
        args.size,
        rankings,
        relevance,
        queries,
        subsets,
        range(1, DEPTH + 1),
        KS,
        default_uncertainty(),  # evaluate.py's: bootstrap intervals of every figure
    )
    recall = tables[0].query("ranking == 'descriptor' and groundtruth == 'relative_pose' and metric == 'recall'")
    localized = [e for e in estimates if e.ranking == "descriptor" and e.method == "bdi"][0]
    errors = localized.errors(queries.qvec, queries.tvec)[0][KS.index(10)]
    print(
        f"sanity: descriptor R@1 {recall['value'].iloc[0]:.2f}, R@50 {recall['value'].iloc[-1]:.2f} (relative pose); "
        f"bdi k=10 median position error {np.nanmedian(errors):.1f} m"
    )
    tracemalloc.stop()

    def descriptors_of(database_rows: np.ndarray, query_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return database_descriptors[database_rows], query_descriptors[query_rows]

    sfm_at_scale(scene, rankings, descriptors_of, args, rng)


def evaluate_config(overrides: list[str]):
    """``configs/evaluate.yaml`` composed with ``overrides``: what ``python evaluate.py`` runs."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name="evaluate", overrides=overrides)


def dataset_sfm(size: str) -> SfmSettings:
    """The ``sfm`` settings of ``python evaluate.py data=<size>`` (its preset and ``sfm`` section)."""
    return validated(SfmSettings, evaluate_config([f"data={size}"]).sfm, "sfm")


def default_paradigms(overrides: list[str]) -> Paradigms:
    """The paradigms ``python evaluate.py`` runs with ``overrides`` (``configs/paradigms/``)."""
    return validated(Paradigms, evaluate_config(overrides).paradigms, "paradigms")


def approximation_paradigm() -> PoseApproximation:
    """Paradigm 1 as ``python evaluate.py`` runs it (every method, its weights), at the k of `KS`."""
    return default_paradigms([f"paradigms.approximation.k=[{','.join(map(str, KS))}]"]).approximation


def sfm_paradigms() -> dict[str, SfmParadigm]:
    """The SfM paradigms ``python evaluate.py`` runs: name -> their stages."""
    return default_paradigms([]).sfm_paradigms()


def sfm_plan(scene: Scene, rankings, sfm: SfmSettings, cache: Path) -> SfmPlan:
    """The exact SfM work of both paradigms for ``rankings``."""
    return count_work(SfmInputs.prepare(scene, sfm, cache, extract=False), rankings, sfm_paradigms())


def with_kapture_root(scene: Scene, root: Path) -> Scene:
    """``scene`` with its images under the kapture folder ``root`` (where `FeatureWorld` writes their features)."""
    records = root / "sensors" / "records_data"
    return Scene(
        scene.name,
        dataclasses.replace(scene.database, image_root=records),
        dataclasses.replace(scene.queries, image_root=records),
        frustum_far=scene.frustum_far,
    )


def measured_unit_costs(
    scene: Scene, sfm: SfmSettings, keypoints: int, rng: np.random.Generator, folder: Path
) -> Calibration:
    """`calibrate` on the scene, the images of its neighbourhood given generated features
    (`FeatureWorld`) at ``keypoints``, written as kapture files under ``folder``."""
    paradigms, scene = sfm_paradigms(), with_kapture_root(scene, folder)
    sample, _ = calibration_sample(scene)
    world = FeatureWorld(np.concatenate([sample.database.centers, sample.queries.centers]), scene.frustum_far, rng)
    for images in (sample.database, sample.queries):
        world.write(images, range(len(images)), keypoints, scene.frustum_far, sfm.features.name)
    return calibrate(scene, sfm, paradigms, folder / "cache")


def sfm_at_scale(scene: Scene, rankings, descriptors_of, args, rng: np.random.Generator) -> None:
    """The SfM paradigms' work for ``rankings``, its forecast at ``args.keypoints``, and a slice forecast then run."""
    sfm = dataset_sfm(args.size)
    processes = sfm.processes
    with tempfile.TemporaryDirectory(prefix="bench_scale-") as folder:
        folder = Path(folder)
        plan = measure("plan: both SfM paradigms", sfm_plan, scene, rankings, sfm, folder / "cache")
        for w in plan.paradigms:
            print(
                f"  {w.paradigm}: query pairs {w.query_pairs.total:,}, database pairs {w.database_pairs.total:,}, "
                f"maps {w.maps.total:,} (~{w.pairs_per_map:,.0f} pairs each), registrations {w.registrations.total:,}"
            )
        costs = measure(
            f"unit costs at {args.keypoints:,} keypoints",
            measured_unit_costs,
            scene,
            sfm,
            args.keypoints,
            rng,
            folder / "units",
        )
        device = sfm.matching.matcher().device
        print(unit_cost_line(costs, args.keypoints, device))
        label = f"projected full SfM sweep ({args.size}, {args.keypoints:,} keypoints"
        print(forecast_line(label, forecast(plan, costs, processes, device), processes))
        ratio = measure(
            "batched against COLMAP triangulation", batched_triangulation_ratio, scene, sfm, args.keypoints, rng
        )
        scaled = {name: seconds * ratio for name, seconds in costs.map_pairs.items()}
        batched = forecast(plan, dataclasses.replace(costs, map_pairs=scaled), processes, device)
        print(
            forecast_line(f"  with sfm/triangulation=batched ({ratio:.2f} of COLMAP's time per map", batched, processes)
        )

        on_gpu = device.startswith("cuda")
        fraction = args.slice if args.slice is not None else (0.02 if on_gpu else 0.005)
        keypoints = args.slice_keypoints or (args.keypoints if on_gpu else 1000)
        slice_scene, slice_rankings = scene_slice(scene, descriptors_of, fraction, args.seed, folder / "slice")
        world = FeatureWorld(
            np.concatenate([slice_scene.database.centers, slice_scene.queries.centers]), scene.frustum_far, rng
        )
        for images in (slice_scene.database, slice_scene.queries):
            world.write(images, range(len(images)), keypoints, scene.frustum_far, sfm.features.name)
        slice_plan = sfm_plan(slice_scene, slice_rankings, sfm, folder / "slice_cache")
        slice_costs = calibrate(slice_scene, sfm, sfm_paradigms(), folder / "slice_cache")
        slice_forecast = forecast(slice_plan, slice_costs, processes, device)
        print(
            f"slice: {len(slice_scene.queries)} queries ({100 * fraction:g} %) "
            f"and {len(slice_scene.database)} database images at "
            f"{keypoints:,} keypoints: {slice_plan.new_pairs():,} pairs, "
            f"{sum(w.maps.new for w in slice_plan.paradigms):,} maps, "
            f"{sum(w.registrations.new for w in slice_plan.paradigms):,} registrations"
        )
        # printed before the run: one cut short by a time limit still shows its forecast
        print(forecast_line("  slice forecast", slice_forecast, processes), flush=True)
        inputs = SfmInputs.prepare(slice_scene, sfm, folder / "slice_cache", extract=False)
        run = run_sfm(inputs, slice_rankings, sfm_paradigms())
        total = sum(slice_forecast.values())
        ratio = run.seconds / total
        print(
            f"  slice measured end to end: {run.seconds:.1f} s ("
            + ", ".join(f"{stage} {record.seconds:.1f} s" for stage, record in run.stages.items())
            + f") against {total:.1f} s forecast: measured / forecast {ratio:.2f} "
            f"({'within' if BAND[0] <= ratio <= BAND[1] else 'outside'} its band x{BAND[0]:g}-{BAND[1]:g})"
        )


def batched_triangulation_ratio(scene: Scene, sfm: SfmSettings, keypoints: int, rng: np.random.Generator) -> float:
    """`BatchedTriangulation`'s time over the configured triangulation's on one map of the first
    database image and its 9 nearest, generated features with their true correspondences."""
    database = scene.database
    near = np.argsort(np.linalg.norm(database.centers - database.centers[0], axis=1), kind="stable")
    images = database.subset(near[:TRIANGULATION_IMAGES])
    world = FeatureWorld(images.centers, scene.frustum_far, rng)
    features = [world.features(images, i, keypoints, scene.frustum_far) for i in range(len(images))]
    matches = {}
    for a in range(len(images)):
        for b in range(a + 1, len(images)):
            shared, rows_a, rows_b = np.intersect1d(features[a][2], features[b][2], return_indices=True)
            matches[(a, b)] = np.column_stack([rows_a, rows_b])[shared >= 0]
    map_input = MapInput(images.cameras, images.qvec, images.tvec, [f[0][:, :2] + 0.5 for f in features], matches)
    batched = BatchedTriangulation(sfm.triangulation.min_angle, sfm.triangulation.max_reprojection_error)
    seconds = []
    for triangulation in (sfm.triangulation, batched):
        triangulation.triangulate_many([map_input])  # first call: imports
        started = time.perf_counter()
        triangulation.triangulate_many([map_input])
        seconds.append(time.perf_counter() - started)
    return seconds[1] / seconds[0]


def unit_cost_line(costs: Calibration, keypoints: int, device: str) -> str:
    units = ", ".join(
        f"{name}: triangulate {costs.map_pairs[name] * 1e3:.2f} ms/map pair, register "
        f"{costs.registered_images[name] * 1e3:.2f} ms/image"
        for name in costs.map_pairs
    )
    return (
        f"  per unit in one process ({keypoints:,} keypoints, matching on {device}, "
        f"measured on {costs.sample}): features {costs.features:.4f} s/image, "
        f"match + verify {costs.pairs * 1e3:.2f} ms/pair, {units}"
    )


def forecast_line(label: str, stages: dict[str, float], processes: int) -> str:
    total = sum(stages.values())
    return (
        f"{label}, {processes} processes): {_hours(total)} ("
        + ", ".join(f"{stage} {_hours(seconds)}" for stage, seconds in stages.items())
        + ")"
    )


def _hours(seconds: float) -> str:
    return f"{seconds / 3600:.2f} h" if seconds >= 3600 else f"{seconds:.1f} s"


def scene_slice(scene: Scene, descriptors_of, fraction: float, seed: int, root: Path) -> tuple[Scene, list]:
    """The ``fraction`` of the queries with the smallest x, the database images within 25 m of
    them (at least 60), and their rankings (faiss, ground truths, random) on that sub-scene."""
    queries = np.argsort(scene.queries.centers[:, 0], kind="stable")[: max(1, round(fraction * len(scene.queries)))]
    centers = scene.queries.centers[queries]
    distance = np.linalg.norm(scene.database.centers[:, None, :2] - centers[None, :, :2], axis=2).min(1)
    database = np.sort(np.argsort(distance, kind="stable")[: max(60, int((distance <= 25.0).sum()))])
    sub = with_kapture_root(
        Scene(
            f"{scene.name}-slice",
            scene.database.subset(database),
            scene.queries.subset(queries),
            frustum_far=scene.frustum_far,
        ),
        root,
    )
    database_descriptors, query_descriptors = descriptors_of(database, queries)
    return sub, scene_rankings(sub, database_descriptors, query_descriptors, np.random.default_rng(seed), seed)[0]


if __name__ == "__main__":
    main()
