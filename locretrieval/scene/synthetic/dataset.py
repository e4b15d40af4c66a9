"""Rendering the whole synthetic dataset: database (mapping) and query kapture folders."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from locretrieval.cache import process_alive
from locretrieval.config import validated
from locretrieval.device import resolve_device
from locretrieval.pool import WORKERS
from locretrieval.scene.synthetic.camera import PinholeCamera
from locretrieval.scene.synthetic.conditions import add_sensor_noise, exposure_path, sample_conditions
from locretrieval.scene.synthetic.config import CONDITIONS, RenderSettings
from locretrieval.scene.synthetic.dynamic import place_dynamic_objects, probe_camera
from locretrieval.scene.synthetic.kapture_writer import WrittenImage, write_image_files, write_kapture_lists
from locretrieval.scene.synthetic.render import Renderer
from locretrieval.scene.synthetic.trajectories import (
    Viewpoint,
    acceptable_view,
    mapping_viewpoints,
    sample_query_viewpoint,
)
from locretrieval.scene.synthetic.world import BoxSet, Environment

#: Independent random streams derived from the seed.
SCENE, MAPPING, QUERIES, EXPOSURE = range(4)
MAX_VIEWPOINT_ATTEMPTS = 500
MAX_OBJECTS = 3
DATABASE_CAMERA = "db_cam"

#: Prefix of the temporary folder a render writes into (``.rendering-<pid>-<random>``).
STAGING_PREFIX = ".rendering-"


@dataclass
class ImagePlan:
    """Everything that decides one image before it is rendered."""

    folder: str  # "mapping" or "query"
    index: int
    camera: PinholeCamera
    viewpoint: Viewpoint
    tags: set[str]
    objects: BoxSet | None

    @property
    def name(self) -> str:
        return f"{'db' if self.folder == 'mapping' else 'query'}/{self.index:06d}.png"


def build_environment(settings: RenderSettings) -> Environment:
    """The scene of ``settings`` (its environment's builder; deterministic in ``seed``)."""
    rng = np.random.default_rng([int(settings.seed), SCENE])
    return settings.builder.build(rng, float(settings.length), int(settings.texture_size))


def cameras(config: RenderSettings) -> tuple[PinholeCamera, list[PinholeCamera]]:
    """Database camera (``PINHOLE``) and query cameras (``SIMPLE_PINHOLE``, one per query FOV)."""
    width, height = int(config.width), int(config.height)
    database = PinholeCamera.centred(DATABASE_CAMERA, "PINHOLE", width, height, float(config.database_fov_deg))
    queries = [
        PinholeCamera.centred(f"query_cam{i}", "SIMPLE_PINHOLE", width, height, float(fov))
        for i, fov in enumerate(config.query_fov_deg)
    ]
    return database, queries


def plan_database(
    config: RenderSettings, environment: Environment, renderer: Renderer, camera: PinholeCamera
) -> list[ImagePlan]:
    """Mapping viewpoints, all ``day``; some with dynamic objects (``database_dynamic``)."""
    rng = np.random.default_rng([int(config.seed), MAPPING])
    plans = []
    for index, viewpoint in enumerate(mapping_viewpoints(environment, int(config.num_database), rng)):
        tags, objects = {"day"}, None
        if rng.random() < float(config.database_dynamic):
            objects = place_dynamic_objects(
                environment,
                renderer,
                camera,
                viewpoint.rotation,
                viewpoint.center,
                int(rng.integers(1, MAX_OBJECTS + 1)),
                rng,
            )
            if len(objects):
                tags.add("dynamic")
            else:
                objects = None
        plans.append(ImagePlan("mapping", index, camera, viewpoint, tags, objects))
    return plans


def plan_queries(
    config: RenderSettings,
    environment: Environment,
    renderer: Renderer,
    query_cameras: list[PinholeCamera],
    mapping: list[Viewpoint],
) -> list[ImagePlan]:
    """Query viewpoints (validated with depth probes) with their sampled conditions."""
    rng = np.random.default_rng([int(config.seed), QUERIES])
    plans = []
    for index in range(int(config.num_queries)):
        tags = sample_conditions(dataclasses.asdict(config.conditions), rng)
        hard = bool(rng.random() < float(config.hard_query_fraction))
        camera = query_cameras[int(rng.integers(len(query_cameras)))]
        for _ in range(MAX_VIEWPOINT_ATTEMPTS):
            viewpoint = sample_query_viewpoint(environment, mapping, hard, rng)
            probe, _ = renderer.geometry(probe_camera(camera), viewpoint.rotation, viewpoint.center)
            if not acceptable_view(environment, viewpoint, probe):
                continue
            objects = None
            if "dynamic" in tags:
                objects = place_dynamic_objects(
                    environment,
                    renderer,
                    camera,
                    viewpoint.rotation,
                    viewpoint.center,
                    int(rng.integers(1, MAX_OBJECTS + 1)),
                    rng,
                )
                if not len(objects):
                    continue
            plans.append(ImagePlan("query", index, camera, viewpoint, tags, objects))
            break
        else:
            raise RuntimeError(
                f"synthetic {environment.name}: no acceptable viewpoint for query {index} after "
                f"{MAX_VIEWPOINT_ATTEMPTS} attempts; is 'length' too small?"
            )
    return plans


def render_plan(
    renderer: Renderer, environment: Environment, plan: ImagePlan, config: RenderSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """uint8 RGB ``[H, W, 3]``, float32 depth ``[H, W]`` and bool dynamic mask of one plan.

    Motion blur averages ``blur_subframes`` sub-frames along the exposure path, rendered at
    half resolution (the blur removes the detail they lack) and upsampled; depth and mask
    come from the mid-exposure pose at full resolution, the mask joined with the objects'
    positions in every sub-frame.
    """
    rng = np.random.default_rng([int(config.seed), EXPOSURE, plan.folder == "query", plan.index])
    lighting = environment.night if "night" in plan.tags else environment.day
    rotation, center = plan.viewpoint.rotation, plan.viewpoint.center
    supersampling = int(config.supersampling)
    if "blur" in plan.tags:
        camera = plan.camera
        low = camera.scaled(-(-camera.width // 2), -(-camera.height // 2))
        path = exposure_path(rotation, center, int(config.blur_subframes), rng)
        frames = [renderer.render(low, R, c, lighting, plan.objects, supersampling) for R, c in path]
        rgb = _resize(np.mean([frame.rgb for frame in frames], axis=0), camera, "bilinear")
        depth, mask = renderer.geometry(camera, rotation, center, plan.objects)
        mask |= (
            _resize(
                np.any([frame.dynamic for frame in frames], axis=0)[..., None].astype(np.float32), camera, "nearest"
            )[..., 0]
            > 0
        )
    else:
        result = renderer.render(plan.camera, rotation, center, lighting, plan.objects, supersampling)
        rgb, depth, mask = result.rgb, result.depth, result.dynamic
    if "noise" in plan.tags:
        rgb = add_sensor_noise(rgb, float(config.noise_std), rng)
    if ("dynamic" in plan.tags) != bool(mask.any()):
        raise RuntimeError(f"synthetic image {plan.name}: dynamic tag and rendered mask disagree")
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8), depth.astype(np.float32), mask


def _resize(image: np.ndarray, camera: PinholeCamera, mode: str) -> np.ndarray:
    """``[h, w, C]`` float32 resampled to the camera's ``[H, W, C]`` (pixel centres aligned)."""
    tensor = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
    kwargs = {"align_corners": False} if mode == "bilinear" else {}
    resized = torch.nn.functional.interpolate(tensor, size=(camera.height, camera.width), mode=mode, **kwargs)
    return resized[0].permute(1, 2, 0).numpy()


@dataclass
class _RenderContext:
    """What rendering one planned image needs (built once per worker process)."""

    config: RenderSettings
    environment: Environment
    renderer: Renderer
    staging: Path

    def __call__(self, plan: ImagePlan) -> None:
        rgb, depth, mask = render_plan(self.renderer, self.environment, plan, self.config)
        write_image_files(self.staging / plan.folder, plan.name, rgb, depth, mask)


#: In a rendering worker: what renders the images of the render in progress.
_WORKER_CONTEXT: list[_RenderContext] = []


def _render_in_worker(shared: tuple[RenderSettings, Path], plan: ImagePlan) -> None:
    """Render one image; the worker builds the scene's renderer once per render."""
    config, staging = shared
    if not _WORKER_CONTEXT or _WORKER_CONTEXT[0].staging != staging:
        torch.set_num_threads(1)
        environment = build_environment(config)
        renderer = Renderer(environment, resolve_device(str(config.device)))
        _WORKER_CONTEXT[:] = [_RenderContext(config, environment, renderer, staging)]
    _WORKER_CONTEXT[0](plan)


def render_synthetic_dataset(settings: RenderSettings, output_dir: str | Path) -> None:
    """Render the synthetic scene of ``settings`` into ``output_dir/{mapping,query}`` (kapture).

    Deterministic in ``settings.seed`` (byte-identical files on the same machine and device).
    ``settings``: a `RenderSettings`, or the ``data.render`` node it is checked from. Poses are
    written world-to-camera. Everything is rendered into a temporary folder and then replaces
    ``mapping/``, ``query/`` and ``synthetic_config.json`` (`RenderSettings.record`) in ``output_dir``.
    """
    settings = validated(RenderSettings, settings, "data.render")
    with single_torch_thread():
        _render(settings, Path(output_dir))


@contextlib.contextmanager
def single_torch_thread() -> Iterator[None]:
    """Run torch single-threaded: the renderer's many small tensor operations gain little
    from intra-op threads and slow down badly when cores are shared; it also keeps the
    floating-point results independent of the caller's thread setting."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _render(config: RenderSettings, output_dir: Path) -> None:
    output_dir.mkdir(parents=True, exist_ok=True)
    WORKERS.start(int(config.workers))  # the workers start (seconds of imports) while this process plans the views
    environment = build_environment(config)
    renderer = Renderer(environment, resolve_device(str(config.device)))
    database_camera, query_cameras = cameras(config)
    database = plan_database(config, environment, renderer, database_camera)
    queries = plan_queries(config, environment, renderer, query_cameras, [plan.viewpoint for plan in database])
    plans = database + queries
    remove_stale_staging(output_dir)
    with tempfile.TemporaryDirectory(dir=output_dir, prefix=f"{STAGING_PREFIX}{os.getpid()}-") as staging:
        staging = Path(staging)
        workers = int(config.workers)
        description = f"rendering synthetic {environment.name}"
        if workers == 1:
            context = _RenderContext(config, environment, renderer, staging)
            for plan in tqdm(plans, desc=description, unit="image"):
                context(plan)
        else:
            for _ in WORKERS.map(_render_in_worker, plans, workers, description, (config, staging)):
                pass
        write_kapture_lists(staging / "mapping", [database_camera], _written(database))
        write_kapture_lists(staging / "query", query_cameras, _written(queries))
        (staging / "synthetic_config.json").write_text(json.dumps(config.record(), indent=2, sort_keys=True) + "\n")
        for entry in ("mapping", "query", "synthetic_config.json"):
            target = output_dir / entry
            if target.is_dir():
                shutil.rmtree(target)
            elif target.exists():
                target.unlink()
            (staging / entry).replace(target)


def remove_stale_staging(output_dir: Path) -> list[Path]:
    """Delete the staging folders (``.rendering-<pid>-*``) of renders whose process is gone
    (killed runs); a live render's folder is left alone. Returns the folders removed."""
    removed = []
    for folder in output_dir.glob(f"{STAGING_PREFIX}*"):
        pid = folder.name.removeprefix(STAGING_PREFIX).split("-", 1)[0]
        if not pid.isdigit() or not process_alive(int(pid)):
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
    return removed


def _written(plans: list[ImagePlan]) -> list[WrittenImage]:
    return [
        WrittenImage(
            plan.name,
            plan.index,
            plan.camera.sensor_id,
            plan.viewpoint.rotation,
            plan.viewpoint.center,
            tuple(sorted(plan.tags, key=_tag_order)),
        )
        for plan in plans
    ]


def _tag_order(tag: str) -> int:
    return ("day", *CONDITIONS).index(tag)
