"""Camera viewpoints: mapping passes for the database and perturbed/free viewpoints for queries."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from locretrieval.scene.synthetic.camera import rotation_from_angles
from locretrieval.scene.synthetic.world import Environment

MAPPING_HEADINGS = (0.0, 90.0, 180.0, 270.0)  # along +x, towards +y, along -x, towards -y
CLEARANCE = 0.4  # metres between a camera centre and any solid box
MIN_MEDIAN_DEPTH = 2.0
MAX_SKY_SHARE = 0.5


@dataclass(frozen=True)
class Viewpoint:
    """A camera centre (world, metres) with heading, elevation and roll in degrees."""

    center: np.ndarray
    yaw: float
    pitch: float
    roll: float

    @property
    def rotation(self) -> np.ndarray:
        """World-to-camera rotation (``x_cam = R (x_world - center)``)."""
        return rotation_from_angles(self.yaw, self.pitch, self.roll)


def mapping_viewpoints(environment: Environment, count: int, rng: np.random.Generator) -> list[Viewpoint]:
    """Database viewpoints as in a mapping rig (Baidu-mall style): stations evenly spaced
    along ``x`` on each mapping lane, four cameras per station looking along and across
    the corridor, with small jitter. The first ``count`` in station order are returned."""
    per_station = len(environment.mapping_lanes) * len(MAPPING_HEADINGS)
    stations = max(2, math.ceil(count / per_station))
    xs = np.linspace(environment.walk_x[0] + 0.5, environment.walk_x[1] - 0.5, stations)
    viewpoints = []
    for x in xs:
        for lane in environment.mapping_lanes:
            for heading in MAPPING_HEADINGS:
                center = np.array(
                    [
                        x + rng.normal(0.0, 0.1),
                        lane + rng.normal(0.0, 0.05),
                        environment.mapping_height + rng.normal(0.0, 0.02),
                    ]
                )
                viewpoints.append(
                    Viewpoint(center, heading + rng.normal(0.0, 3.0), rng.normal(0.0, 2.0), rng.normal(0.0, 1.0))
                )
    return viewpoints[:count]


def sample_query_viewpoint(
    environment: Environment, mapping: list[Viewpoint], hard: bool, rng: np.random.Generator
) -> Viewpoint:
    """One candidate query viewpoint (validate it with :func:`acceptable_view`).

    Ordinary queries perturb a random database viewpoint (about 1 m, 12 degrees of heading,
    other heights as from a phone); hard ones are anywhere, in any direction, tilted more.
    """
    if hard:
        x = rng.uniform(*environment.walk_x)
        y = rng.uniform(*environment.walk_y)
        return Viewpoint(
            np.array([x, y, rng.uniform(1.0, 2.2)]),
            rng.uniform(0.0, 360.0),
            rng.normal(0.0, 10.0),
            rng.normal(0.0, 6.0),
        )
    anchor = mapping[rng.integers(len(mapping))]
    x = np.clip(anchor.center[0] + rng.normal(0.0, 1.0), *environment.walk_x)
    y = np.clip(anchor.center[1] + rng.normal(0.0, 0.6), *environment.walk_y)
    return Viewpoint(
        np.array([x, y, rng.uniform(1.3, 1.9)]),
        anchor.yaw + rng.normal(0.0, 12.0),
        rng.normal(0.0, 5.0),
        rng.normal(0.0, 3.0),
    )


def acceptable_view(environment: Environment, viewpoint: Viewpoint, probe_depth: np.ndarray) -> bool:
    """The camera is clear of solid boxes and sees mostly scene (not a wall at arm's length, not sky)."""
    if environment.boxes.contains(viewpoint.center[None], margin=CLEARANCE).any():
        return False
    seen = probe_depth[probe_depth > 0]
    return seen.size >= (1.0 - MAX_SKY_SHARE) * probe_depth.size and float(np.median(seen)) >= MIN_MEDIAN_DEPTH
