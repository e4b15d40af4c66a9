"""Paradigms 2a/2b speed on the built-in synthetic scene (default: 128 database + 64 queries, 480x360).

    .venv/bin/python benchmarks/bench_sfm.py [--cache-dir .cache] [--workers 2] [--queries 64]

Prints SIFT extraction images/s, matching ms/pair, the per-query time of local SfM (k=10)
and global SfM (k=5) once features and matches are cached, and the time of one sweep over
all k against the sum of separate runs per k (each from an empty match cache). The scene is
rendered into ``<cache-dir>/synthetic`` on first use; SfM caches go to a temporary folder.
"""

import argparse
import dataclasses
import logging
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

import locretrieval  # noqa: F401  (imports zlib before pycolmap)
from locretrieval.config import validated
from locretrieval.groundtruth import relative_pose_groundtruth
from locretrieval.paradigms import global_sfm, local_sfm
from locretrieval.paradigms.global_sfm import GlobalSfm
from locretrieval.paradigms.local_sfm import DatabaseMapMatches, LocalSfm
from locretrieval.pool import resolve_workers
from locretrieval.retrieval import random_ranking
from locretrieval.scene import Scene
from locretrieval.sfm.features import extract_features
from locretrieval.sfm.inputs import SfmInputs
from locretrieval.sfm.matching import PairMatcher
from locretrieval.sfm.pose_cache import PoseCache
from locretrieval.sfm.query_tasks import query_tasks
from locretrieval.sfm.settings import SfmSettings

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
LOCAL_KS, GLOBAL_KS = [5, 10, 20], [1, 5, 10, 20, 50]


def timed(function, *args, **kwargs) -> tuple[float, object]:
    start = time.perf_counter()
    result = function(*args, **kwargs)
    return time.perf_counter() - start, result


def fresh_cache(features_from: Path) -> Path:
    """A new cache folder beside ``features_from`` holding only its features (so matching starts from nothing)."""
    folder = Path(tempfile.mkdtemp(dir=features_from.parent))
    shutil.copytree(features_from / "features", folder / "features")
    return folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--cache-dir", type=Path, default=Path(".cache"), help="where the synthetic scene is (rendered if missing)"
    )
    parser.add_argument("--workers", type=int, default=0, help="worker processes (0: one per core)")
    parser.add_argument("--queries", type=int, default=64, help="queries of the scene used")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    workers = resolve_workers(args.workers)

    # configs/evaluate.yaml's scene and sfm settings, so that `make evaluate`'s scene is reused
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(
            "evaluate",
            [f"paths.cache_dir={args.cache_dir.resolve()}", "paths.root_dir=.", f"data.render.workers={workers}"],
        )
    full = instantiate(cfg.data)
    scene = Scene(
        full.name,
        full.database,
        full.queries.subset(np.arange(min(args.queries, len(full.queries)))),
        frustum_far=full.frustum_far,
    )
    camera = scene.database.cameras[0]
    print(
        f"scene: {len(scene.database)} database images, {len(scene.queries)} "
        f"queries, {camera.width}x{camera.height}, {workers} worker(s)"
    )
    sfm = validated(SfmSettings, cfg.sfm, "sfm")
    with tempfile.TemporaryDirectory(prefix="bench_sfm-") as root:
        benchmark(scene, Path(root) / "base", sfm, workers)


def benchmark(scene: Scene, base: Path, sfm: SfmSettings, workers: int) -> None:
    database, queries = scene.database, scene.queries
    features = sfm.features
    serial, _ = timed(extract_features, database.subset(np.arange(16)), features, base / "serial", 1)
    print(f"SIFT (pycolmap, CPU, 1 process): {16 / serial:.1f} images/s")
    elapsed, _ = timed(extract_features, database, features, base, workers)
    elapsed_queries, _ = timed(extract_features, queries, features, base, workers)
    total = len(database) + len(queries)
    print(
        f"SIFT, {workers} worker(s), {total} images (pool start included): "
        f"{total / (elapsed + elapsed_queries):.1f} images/s"
    )

    groundtruth = relative_pose_groundtruth(
        database, queries, depth=50, position_threshold=25.0, rotation_threshold=45.0
    ).ranking
    rankings = [groundtruth, random_ranking(len(queries), len(database), 50, 0)]
    parallel = dataclasses.replace(sfm, workers=workers)
    query_features, database_features = (extract_features(images, features, base, 1) for images in (queries, database))
    matcher = PairMatcher(queries, query_features, database, database_features, sfm.matching, base)
    pairs = [
        (queries.names[q], database.names[i]) for q in range(min(8, len(queries))) for i in range(0, len(database), 2)
    ]
    elapsed, matched = timed(matcher.ensure, pairs, 1)
    print(f"matching (mutual NN + ratio, 1 process): {1000 * elapsed / matched:.1f} ms/pair")

    paradigms = (
        ("local_sfm", LOCAL_KS, lambda ks: LocalSfm(True, ks, DatabaseMapMatches()), local_sfm.register_query_in_maps),
        ("global_sfm", GLOBAL_KS, lambda ks: GlobalSfm(True, ks, None), global_sfm.register_query_in_map),
    )
    for name, ks, paradigm, register in paradigms:
        cache = fresh_cache(base)
        sweep, _ = timed(paradigm(ks).run, scene, rankings, parallel, cache)
        separate = sum(timed(paradigm([k]).run, scene, rankings, parallel, fresh_cache(base))[0] for k in ks)
        print(f"{name}: one sweep over k={ks}, 2 rankings: {sweep:.1f} s; separate runs per k: {separate:.1f} s in all")

        inputs = SfmInputs.prepare(scene, dataclasses.replace(sfm, workers=1), cache)
        k = 10 if name == "local_sfm" else 5
        maps = Path(tempfile.mkdtemp(dir=base.parent)) / "local_maps"  # triangulated again, not read
        shared = (
            (inputs, DatabaseMapMatches(), maps)
            if name == "local_sfm"
            else (inputs, global_sfm.global_map(inputs, None, cache))
        )
        tasks = query_tasks([groundtruth], [[k]], PoseCache(None, queries.names, database.names))
        elapsed, _ = timed(lambda: [register(shared, task) for task in tasks])
        print(
            f"{name}: {1000 * elapsed / len(tasks):.0f} ms per query at k={k} "
            "(cached features and matches, 1 process; local maps triangulated)"
        )


if __name__ == "__main__":
    main()
