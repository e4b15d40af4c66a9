"""Synthetic renderer speed: seconds per image of the default config, per condition.

    .venv/bin/python benchmarks/bench_render.py [--environment mall street] [--images 8] [--full]

Renders ``--images`` planned images of each kind (database day, query night, blur, noise,
dynamic) in this process, single-threaded as the dataset renderer runs, and prints wall and
CPU seconds per image. ``--full`` also renders the whole default dataset into a temporary
folder with ``render_synthetic_dataset`` and prints its total wall time and the CPU time of
all processes (the default config renders with 2 worker processes).
"""

import argparse
import dataclasses
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import locretrieval  # noqa: F401
from locretrieval.config import validated
from locretrieval.device import resolve_device
from locretrieval.scene.synthetic import RenderSettings, render_synthetic_dataset
from locretrieval.scene.synthetic.dataset import (
    ImagePlan,
    build_environment,
    cameras,
    plan_database,
    render_plan,
    single_torch_thread,
)
from locretrieval.scene.synthetic.dynamic import place_dynamic_objects
from locretrieval.scene.synthetic.render import Renderer


def render_settings(**changes) -> RenderSettings:
    """``data.render`` as ``configs/data/synthetic.yaml`` sets it (on the CPU), ``changes`` applied."""
    configs = Path(__file__).resolve().parents[1] / "configs"
    with initialize_config_dir(config_dir=str(configs), version_base="1.3"):
        render = compose("evaluate", ["device=cpu", "paths.root_dir=/nonexistent"]).data.render
    return validated(RenderSettings, {**OmegaConf.to_container(render, resolve=True), **changes}, "data.render")


def cpu_seconds() -> float:
    """CPU time of this process and of its finished children."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def per_image(environment_name: str, images: int) -> None:
    config = render_settings(environment=environment_name, num_database=images)
    start = time.perf_counter()
    environment = build_environment(config)
    renderer = Renderer(environment, resolve_device(config.device))
    print(
        f"{environment_name}: scene + textures ({config.texture_size} px) built in {time.perf_counter() - start:.2f} s"
    )
    database_camera, query_cameras = cameras(config)
    plans = plan_database(dataclasses.replace(config, database_dynamic=0.0), environment, renderer, database_camera)
    rng = np.random.default_rng(0)
    kinds = {
        "database day": ({"day"}, database_camera),
        "query night": ({"night"}, query_cameras[0]),
        "query blur": ({"day", "blur"}, query_cameras[0]),
        "query noise": ({"day", "noise"}, query_cameras[0]),
        "query dynamic": ({"day", "dynamic"}, query_cameras[0]),
    }
    for kind, (tags, camera) in kinds.items():
        wall, cpu = time.perf_counter(), cpu_seconds()
        for plan in plans:
            viewpoint, image_tags, objects = plan.viewpoint, set(tags), None
            if "dynamic" in tags:
                objects = place_dynamic_objects(
                    environment, renderer, camera, viewpoint.rotation, viewpoint.center, 3, rng
                )
                if not len(objects):
                    image_tags, objects = {"day"}, None
            render_plan(
                renderer, environment, ImagePlan("query", plan.index, camera, viewpoint, image_tags, objects), config
            )
        n = len(plans)
        print(
            f"  {kind:14s} {config.width}x{config.height}: "
            f"{(time.perf_counter() - wall) / n:.3f} s/image wall, "
            f"{(cpu_seconds() - cpu) / n:.3f} s/image CPU ({n} images)"
        )


def full(environment_name: str) -> None:
    config = render_settings(environment=environment_name)
    total = config.num_database + config.num_queries
    with tempfile.TemporaryDirectory() as folder:
        wall, cpu = time.perf_counter(), cpu_seconds()
        render_synthetic_dataset(config, folder)
        wall, cpu = time.perf_counter() - wall, cpu_seconds() - cpu
    print(
        f"{environment_name}: default dataset ({total} images, {config.workers} workers): "
        f"{wall:.1f} s wall, {cpu:.1f} s CPU of all processes, {wall / total:.3f} s/image wall"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--environment", nargs="+", default=["mall", "street"])
    parser.add_argument("--images", type=int, default=8)
    parser.add_argument("--full", action="store_true")
    args = parser.parse_args()
    with single_torch_thread():
        for name in args.environment:
            per_image(name, args.images)
    if args.full:
        for name in args.environment:
            full(name)


if __name__ == "__main__":
    main()
