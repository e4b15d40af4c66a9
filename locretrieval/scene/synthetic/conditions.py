"""Capture conditions of an image: night illumination, motion blur, dynamic objects, noise.

Each image gets ``day`` or ``night`` and any of ``blur``, ``dynamic``, ``noise``, drawn
independently with the configured per-image probabilities.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from locretrieval.scene.synthetic.camera import axis_angle_matrix
from locretrieval.scene.synthetic.config import CONDITIONS

SHOT_NOISE = 0.003  # variance per unit of signal, added to the read-noise variance


def sample_conditions(probabilities: Mapping[str, float], rng: np.random.Generator) -> set[str]:
    """Tags drawn independently: ``night`` (else ``day``), ``blur``, ``dynamic``, ``noise``."""
    draws = {name: bool(rng.random() < probabilities[name]) for name in CONDITIONS}
    tags = {name for name, drawn in draws.items() if drawn}
    tags.add("night" if draws["night"] else "day")
    return tags


def exposure_path(
    rotation: np.ndarray, center: np.ndarray, subframes: int, rng: np.random.Generator
) -> list[tuple[np.ndarray, np.ndarray]]:
    """World-to-camera rotations and centres of ``subframes`` instants of one exposure.

    The camera shakes by a random rotation of 0.5-1.5 degrees (camera frame) and moves
    3-12 cm during the exposure, uniformly in time; the middle sub-frame is the given
    (mid-exposure) pose, which is the pose written for the image.
    """
    axis = rng.normal(size=3)
    spin = axis / np.linalg.norm(axis) * np.radians(rng.uniform(0.5, 1.5))
    heading = rng.normal(size=3) * np.array([1.0, 1.0, 0.3])
    shift = heading / np.linalg.norm(heading) * rng.uniform(0.03, 0.12)
    path = []
    for tau in np.linspace(-0.5, 0.5, subframes):
        path.append((axis_angle_matrix(tau * spin) @ rotation, center + tau * shift))
    return path


def add_sensor_noise(rgb: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian read noise of ``std`` plus signal-dependent shot noise (values in ``[0, 1]``)."""
    sigma = np.sqrt(std * std + SHOT_NOISE * np.clip(rgb, 0.0, None))
    return rgb + sigma * rng.standard_normal(rgb.shape, dtype=np.float32)
