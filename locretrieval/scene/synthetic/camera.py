"""Pinhole cameras in COLMAP's pixel convention and camera orientations.

World frame: metres, ``x`` along the corridor/street, ``y`` across it, ``z`` up.
Camera frame (COLMAP/OpenCV): ``x`` right, ``y`` down, ``z`` forward (optical axis).
Pixel convention (COLMAP): the centre of the first pixel is at ``(0.5, 0.5)``, so pixel
``(column i, row j)`` is centred at ``u = i + 0.5, v = j + 0.5`` and a centred principal
point is ``(W / 2, H / 2)``. Projection: ``u = fx * x / z + cx``, ``v = fy * y / z + cy``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class PinholeCamera:
    """A camera sensor: kapture/COLMAP model ``PINHOLE`` (fx, fy, cx, cy) or ``SIMPLE_PINHOLE``."""

    sensor_id: str
    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def centred(cls, sensor_id: str, model: str, width: int, height: int, hfov_deg: float) -> "PinholeCamera":
        """Square-pixel camera with horizontal field of view ``hfov_deg`` and a centred principal point."""
        focal = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        return cls(sensor_id, model, width, height, focal, focal, width / 2.0, height / 2.0)

    @property
    def params(self) -> list[float]:
        """Parameters in the order of the COLMAP model."""
        if self.model == "SIMPLE_PINHOLE":
            return [self.fx, self.cx, self.cy]
        return [self.fx, self.fy, self.cx, self.cy]

    def scaled(self, width: int, height: int) -> "PinholeCamera":
        """The same field of view at another resolution (used for cheap depth probes)."""
        sx, sy = width / self.width, height / self.height
        return PinholeCamera(
            self.sensor_id, self.model, width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy
        )

    def ray_directions(self, samples_per_axis: int, device: torch.device) -> torch.Tensor:
        """Camera-frame ray directions ``[H * s, W * s, 3]`` with ``z = 1``.

        Sub-pixel sample ``(a, b)`` of pixel ``(i, j)`` sits at ``u = i + (a + 0.5) / s``,
        ``v = j + (b + 0.5) / s``; for ``s = 1`` that is the pixel centre. Because ``z = 1``,
        the ray parameter of a hit equals its depth along the optical axis.
        """
        s = samples_per_axis
        u = (torch.arange(self.width * s, device=device, dtype=torch.float64) + 0.5) / s
        v = (torch.arange(self.height * s, device=device, dtype=torch.float64) + 0.5) / s
        x = ((u - self.cx) / self.fx).to(torch.float32)
        y = ((v - self.cy) / self.fy).to(torch.float32)
        grid_y, grid_x = torch.meshgrid(y, x, indexing="ij")
        return torch.stack([grid_x, grid_y, torch.ones_like(grid_x)], dim=-1)


def rotation_from_angles(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """World-to-camera rotation ``R`` (``x_cam = R @ (x_world - c)``) of a camera whose
    optical axis has heading ``yaw`` (from +x towards +y) and elevation ``pitch``, rolled by
    ``roll`` about the optical axis (positive roll turns the camera's right axis downwards)."""
    yaw, pitch, roll = np.radians([yaw_deg, pitch_deg, roll_deg])
    forward = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rolled_right = math.cos(roll) * right + math.sin(roll) * down
    rolled_down = np.cross(forward, rolled_right)
    return np.stack([rolled_right, rolled_down, forward])


def axis_angle_matrix(axis_angle: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (radians), by Rodrigues' formula."""
    angle = float(np.linalg.norm(axis_angle))
    if angle == 0.0:
        return np.eye(3)
    k = np.asarray(axis_angle, dtype=np.float64) / angle
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)
