"""Dynamic occluders: people-like and vehicle-like textured boxes placed inside a view."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from locretrieval.scene.synthetic.camera import PinholeCamera
from locretrieval.scene.synthetic.world import BoxSet, BoxSetBuilder, Environment, Surface

if TYPE_CHECKING:
    from locretrieval.scene.synthetic.render import Renderer

PROBE_SIZE = (64, 48)
PERSON_HALF = 0.3  # largest horizontal half-extent, metres
VEHICLE_HALF = 2.2
MIN_DISTANCE = 1.3
MAX_DISTANCE = 9.0
VEHICLE_SHARE = 0.35


def probe_camera(camera: PinholeCamera) -> PinholeCamera:
    """The low-resolution camera of depth probes of ``camera``'s view (same field of view)."""
    return camera.scaled(*PROBE_SIZE)


def add_person(builder: BoxSetBuilder, environment: Environment, rng: np.random.Generator, x: float, y: float) -> None:
    """Legs, torso and head boxes (1.5-1.9 m tall) in clothes and skin textures."""
    scale = rng.uniform(0.88, 1.12)
    legs, torso = rng.choice(environment.clothes_textures, size=2)
    head = int(rng.choice(environment.head_textures))
    cloth = (0.5, 0.5)
    builder.add(
        [x - 0.17, y - 0.11, 0.0], [x + 0.17, y + 0.11, 0.85 * scale], Surface(int(legs), period=cloth), dynamic=True
    )
    builder.add(
        [x - 0.25, y - 0.15, 0.85 * scale],
        [x + 0.25, y + 0.15, 1.45 * scale],
        Surface(int(torso), period=cloth),
        dynamic=True,
    )
    builder.add([x - 0.1, y - 0.11, 1.45 * scale], [x + 0.1, y + 0.11, 1.7 * scale], Surface(head), dynamic=True)


def add_vehicle(builder: BoxSetBuilder, environment: Environment, rng: np.random.Generator, x: float, y: float) -> None:
    """A car along ``x``: painted body, glass cabin and a dark underbody."""
    body = Surface(int(rng.choice(environment.vehicle_textures)))
    glass = Surface(environment.glass_texture, period=(1.0, 1.0))
    builder.add([x - 1.9, y - 0.8, 0.0], [x + 1.9, y + 0.8, 0.3], glass, dynamic=True)
    builder.add([x - 2.1, y - 0.9, 0.3], [x + 2.1, y + 0.9, 1.2], body, dynamic=True)
    builder.add([x - 1.1, y - 0.8, 1.2], [x + 0.9, y + 0.8, 1.7], glass, dynamic=True)


def place_dynamic_objects(
    environment: Environment,
    renderer: "Renderer",
    camera: PinholeCamera,
    rotation: np.ndarray,
    center: np.ndarray,
    count: int,
    rng: np.random.Generator,
    attempts: int = 40,
) -> BoxSet:
    """Up to ``count`` people/vehicles standing in free space and visible from the camera.

    From a low-resolution depth probe of the view (:func:`probe_camera`), each object is put
    on the ground along the horizontal direction of a random probe column, closer than the
    nearest surface seen in that column's middle rows. It is kept if it collides with no
    static box nor earlier object (vehicles must be on the road) and the probe sees it.
    """
    probe = probe_camera(camera)
    probe_depth, _ = renderer.geometry(probe, rotation, center)
    rows = slice(PROBE_SIZE[1] // 3, 2 * PROBE_SIZE[1] // 3)
    builder = BoxSetBuilder()
    placed: list[np.ndarray] = []
    for _ in range(attempts):
        if len(placed) == count:
            break
        column = int(rng.integers(PROBE_SIZE[0] // 8, PROBE_SIZE[0] - PROBE_SIZE[0] // 8))
        direction = rotation.T @ np.array([(column + 0.5 - probe.cx) / probe.fx, 0.0, 1.0])
        horizontal = float(np.linalg.norm(direction[:2]))
        depths = probe_depth[rows, column]
        free = (depths.min() if (depths > 0).all() else MAX_DISTANCE / horizontal) * horizontal
        vehicle = bool(environment.vehicle_textures) and rng.random() < VEHICLE_SHARE
        half = VEHICLE_HALF if vehicle else PERSON_HALF
        farthest = min(MAX_DISTANCE, free - half - 0.3)
        if farthest <= MIN_DISTANCE + half:
            continue
        distance = rng.uniform(MIN_DISTANCE + half, farthest)
        x, y = center[:2] + distance * direction[:2] / horizontal
        if not _free_spot(environment, x, y, half, vehicle, placed):
            continue
        candidate = BoxSetBuilder()
        (add_vehicle if vehicle else add_person)(candidate, environment, rng, x, y)
        _, visible = renderer.geometry(probe, rotation, center, candidate.build())
        if visible.any():
            builder.rows.extend(candidate.rows)
            placed.append(np.array([x, y, half]))
    return builder.build()


def _free_spot(
    environment: Environment, x: float, y: float, half: float, vehicle: bool, placed: list[np.ndarray]
) -> bool:
    if vehicle:
        if environment.road_y is None or not environment.road_y[0] <= y <= environment.road_y[1]:
            return False
    elif not (
        environment.walk_x[0] - 1.0 <= x <= environment.walk_x[1] + 1.0
        and environment.walk_y[0] - 0.5 <= y <= environment.walk_y[1] + 0.5
    ):
        return False
    for other in placed:
        if np.hypot(x - other[0], y - other[1]) < half + other[2] + 0.2:
            return False
    samples = np.array([[x, y, z] for z in (0.5, 1.0, 1.5)])
    return not environment.boxes.contains(samples, margin=half).any()
