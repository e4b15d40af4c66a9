"""Vectorised ray casting of box scenes with torch: colour, z-depth and dynamic-object masks.

Rays are generated in COLMAP's pixel convention (see :mod:`.camera`) with camera-frame
direction ``(x, y, 1)``, so the ray parameter of a hit is its depth along the optical axis.
Poses are world-to-camera: ``x_cam = R (x_world - c)``.

Speed: the sample grid is cut into 8 x 8 tiles; each tile is only tested against the boxes
whose projected bounding rectangle (after clipping to the near plane) overlaps it, and tiles
with similar candidate counts are traced together as dense ``[tiles, rays, boxes]`` tensors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from locretrieval.scene.synthetic.atlas import TextureAtlas
from locretrieval.scene.synthetic.camera import PinholeCamera
from locretrieval.scene.synthetic.world import FACE_FRAMES, SKY, BoxSet, Environment, Lighting

TILE = 8
ELEMENTS_PER_BATCH = 1 << 22  # rays x candidate boxes traced at once
RAYS_PER_CHUNK = 1 << 16  # rays shaded at once
NEAR = 0.01
HIT_EPSILON = 1e-4
#: Mip level = log2 of the texel footprint's major axis / ANISOTROPY, at least its minor axis.
ANISOTROPY = 2.0
CLOUD_SCALE = 0.12  # cloud texture periods per unit of (d_x / d_z, d_y / d_z) on the sky plane
EDGES = np.array([(a, a | bit) for a in range(8) for bit in (1, 2, 4) if not a & bit])


@dataclass
class RenderResult:
    """``rgb [H, W, 3]`` float32 (1.0 = white, may exceed it), ``depth [H, W]`` float32 in
    metres along the optical axis (0 where the sky is seen), ``dynamic [H, W]`` bool."""

    rgb: np.ndarray
    depth: np.ndarray
    dynamic: np.ndarray


@dataclass
class _View:
    """One camera pose and sampling rate, with the scene's boxes as device tensors."""

    camera: PinholeCamera
    rotation: np.ndarray  # world-to-camera
    center: np.ndarray
    samples: int
    boxes: BoxSet
    tensors: dict[str, torch.Tensor]

    @property
    def grid(self) -> tuple[int, int]:
        return self.camera.height * self.samples, self.camera.width * self.samples


class Renderer:
    """Renders an :class:`Environment` (plus per-image extra boxes) from pinhole cameras."""

    def __init__(self, environment: Environment, device: torch.device):
        if not environment.boxes.inside.any():
            raise ValueError(f"environment {environment.name!r} has no room box: some rays would hit nothing")
        self.environment = environment
        self.device = device
        self.atlas = TextureAtlas(environment.textures, device)
        self.frames = torch.tensor(FACE_FRAMES, dtype=torch.float32, device=device)

    # --- public API ----------------------------------------------------------------------------

    def render(
        self,
        camera: PinholeCamera,
        rotation: np.ndarray,
        center: np.ndarray,
        lighting: Lighting,
        extra: BoxSet | None = None,
        supersampling: int = 1,
    ) -> RenderResult:
        """Colour, depth and dynamic mask of one view; ``supersampling`` s renders s x s
        samples per pixel for colour and the mask (a pixel is dynamic if any sample is);
        depth is always traced through pixel centres."""
        view = self._view(camera, rotation, center, extra, supersampling)
        directions = self._directions(view)
        t, box, face = self._trace(view, directions)
        flat = box * 6 + face
        sky = view.tensors["texture"][flat] == SKY
        colours = [
            self._shade(view, *chunk, lighting)
            for chunk in zip(*(x.split(RAYS_PER_CHUNK) for x in (directions, t, box, face)))
        ]
        s = supersampling
        shape = (camera.height, s, camera.width, s)
        rgb = torch.cat(colours).reshape(*shape, 3).mean(dim=(1, 3))
        mask = (view.tensors["dynamic"][box] & ~sky).reshape(shape).any(dim=3).any(dim=1)
        if s % 2:
            depth = torch.where(sky, torch.zeros_like(t), t).reshape(shape)[:, s // 2, :, s // 2].cpu().numpy()
        else:
            depth, _ = self.geometry(camera, rotation, center, extra)
        return RenderResult(rgb.cpu().numpy(), depth, mask.cpu().numpy())

    def geometry(
        self, camera: PinholeCamera, rotation: np.ndarray, center: np.ndarray, extra: BoxSet | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Depth ``[H, W]`` (0 on the sky) and dynamic mask through pixel centres, without
        shading (also used as a cheap low-resolution probe to place cameras and objects)."""
        view = self._view(camera, rotation, center, extra, 1)
        t, box, face = self._trace(view, self._directions(view))
        sky = view.tensors["texture"][box * 6 + face] == SKY
        depth = torch.where(sky, torch.zeros_like(t), t).reshape(view.grid)
        dynamic = (view.tensors["dynamic"][box] & ~sky).reshape(view.grid)
        return depth.cpu().numpy(), dynamic.cpu().numpy()

    # --- set-up --------------------------------------------------------------------------------

    def _view(self, camera, rotation, center, extra, samples) -> _View:
        boxes = self.environment.boxes if extra is None else self.environment.boxes.concat(extra)
        arrays = {
            "lo": boxes.lo,
            "hi": boxes.hi,
            "inside": boxes.inside,
            "dynamic": boxes.dynamic,
            "texture": boxes.texture.reshape(-1),
            "u_origin": boxes.u_origin.reshape(-1),
            "v_origin": boxes.v_origin.reshape(-1),
            "u_period": boxes.u_period.reshape(-1),
            "v_period": boxes.v_period.reshape(-1),
            "lit_fraction": boxes.lit_fraction.reshape(-1),
        }
        tensors = {
            key: torch.from_numpy(value.astype(np.float32) if value.dtype == np.float64 else value).to(self.device)
            for key, value in arrays.items()
        }
        tensors["rotation"] = torch.tensor(rotation, dtype=torch.float32, device=self.device)
        tensors["center"] = torch.tensor(center, dtype=torch.float32, device=self.device)
        return _View(camera, np.asarray(rotation, np.float64), np.asarray(center, np.float64), samples, boxes, tensors)

    def _directions(self, view: _View) -> torch.Tensor:
        """World-frame ray directions ``[N, 3]`` (``R^T (x, y, 1)``), row-major over samples."""
        local = view.camera.ray_directions(view.samples, self.device).reshape(-1, 3)
        R = view.tensors["rotation"]
        return local[:, :1] * R[0] + local[:, 1:2] * R[1] + local[:, 2:3] * R[2]

    # --- ray casting ---------------------------------------------------------------------------

    def _trace(self, view: _View, directions: torch.Tensor):
        """Nearest hit of every ray (row-major sample order): ray parameter, box and face."""
        rows, columns = view.grid
        tiles_y, tiles_x = -(-rows // TILE), -(-columns // TILE)
        padded = torch.zeros(tiles_y * TILE, tiles_x * TILE, 3, device=self.device)
        padded[:rows, :columns] = directions.reshape(rows, columns, 3)
        padded[rows:, :, 2] = 1.0
        padded[:, columns:, 2] = 1.0
        tiled = padded.reshape(tiles_y, TILE, tiles_x, TILE, 3).permute(0, 2, 1, 3, 4).reshape(-1, TILE * TILE, 3)
        candidates = self._tile_candidates(view, tiles_y, tiles_x)  # [tiles, B] bool
        counts = candidates.sum(axis=1)
        t_tiled = torch.empty(tiled.shape[:2], device=self.device)
        box_tiled = torch.empty(tiled.shape[:2], dtype=torch.int64, device=self.device)
        for count in np.unique(counts):  # tiles with equally many candidates form dense batches
            group = np.flatnonzero(counts == count)
            per_batch = max(1, ELEMENTS_PER_BATCH // (TILE * TILE * int(count)))
            for tiles in np.array_split(group, -(-len(group) // per_batch)):
                lists = np.nonzero(candidates[tiles])[1].reshape(len(tiles), int(count))
                index = torch.from_numpy(tiles).to(self.device)
                t_hit, box = self._nearest(view, tiled[index], torch.from_numpy(lists).to(self.device))
                t_tiled[index], box_tiled[index] = t_hit, box

        def untile(x: torch.Tensor) -> torch.Tensor:
            image = x.reshape(tiles_y, tiles_x, TILE, TILE).permute(0, 2, 1, 3).reshape(tiles_y * TILE, tiles_x * TILE)
            return image[:rows, :columns].reshape(-1)

        t_hit, box = untile(t_tiled), untile(box_tiled)
        return t_hit, box, self._faces(view, directions, box)

    def _nearest(self, view: _View, directions, lists):
        """Slab test of rays ``[G, R, 3]`` against candidate boxes ``[G, K]``: nearest ``t``, box.

        A solid box is hit where the ray enters it, a room where the ray leaves it.
        """
        safe = torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
        inverse = 1.0 / safe
        origin = view.tensors["center"]
        lo, hi = view.tensors["lo"][lists], view.tensors["hi"][lists]  # [G, K, 3]
        near = far = None
        for axis in range(3):
            inv = inverse[:, :, axis, None]  # [G, R, 1]
            t_lo = (lo[:, None, :, axis] - origin[axis]) * inv  # [G, R, K]
            t_hi = (hi[:, None, :, axis] - origin[axis]) * inv
            entry, leave = torch.minimum(t_lo, t_hi), torch.maximum(t_lo, t_hi)
            near = entry if near is None else torch.maximum(near, entry)
            far = leave if far is None else torch.minimum(far, leave)
        inside = view.tensors["inside"][lists][:, None, :]
        t = torch.where(inside, far, near)
        valid = (near <= far) & (t > HIT_EPSILON)
        t = torch.where(valid, t, torch.full_like(t, float("inf")))
        t_hit, slot = t.min(dim=2)
        return t_hit, lists.gather(1, slot)

    @staticmethod
    def _faces(view: _View, directions: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
        """Face index ``2 * axis + side`` of each ray's hit on its box."""
        inverse = 1.0 / torch.where(directions.abs() < 1e-12, torch.full_like(directions, 1e-12), directions)
        origin = view.tensors["center"]
        inside = view.tensors["inside"][box]
        t_lo = (view.tensors["lo"][box] - origin) * inverse
        t_hi = (view.tensors["hi"][box] - origin) * inverse
        axis = torch.where(inside, torch.maximum(t_lo, t_hi).argmin(dim=1), torch.minimum(t_lo, t_hi).argmax(dim=1))
        positive = directions.gather(1, axis[:, None])[:, 0] > 0
        return 2 * axis + (positive == inside).long()

    @staticmethod
    def _tile_candidates(view: _View, tiles_y: int, tiles_x: int) -> np.ndarray:
        """``[tiles, B]``: boxes whose projection may cover each tile (rooms cover all)."""
        camera, s = view.camera, view.samples
        corners = (view.boxes.corners() - view.center) @ view.rotation.T  # [B, 8, 3] camera frame
        a, b = corners[:, EDGES[:, 0]], corners[:, EDGES[:, 1]]
        crossing = (a[..., 2] - NEAR) * (b[..., 2] - NEAR) < 0
        span = np.where(crossing, b[..., 2] - a[..., 2], 1.0)
        fraction = np.where(crossing, (NEAR - a[..., 2]) / span, 0.0)
        clipped = a + fraction[..., None] * (b - a)
        points = np.concatenate([corners, clipped], axis=1)
        valid = np.concatenate([corners[..., 2] >= NEAR, crossing], axis=1)
        depth = np.where(valid, points[..., 2], 1.0)
        u = np.where(valid, (camera.fx * points[..., 0] / depth + camera.cx) * s, np.nan)
        v = np.where(valid, (camera.fy * points[..., 1] / depth + camera.cy) * s, np.nan)
        seen = valid.any(axis=1)
        with np.errstate(invalid="ignore"):
            u0, u1 = np.nanmin(np.where(seen[:, None], u, 0), 1) - 1, np.nanmax(np.where(seen[:, None], u, 0), 1) + 1
            v0, v1 = np.nanmin(np.where(seen[:, None], v, 0), 1) - 1, np.nanmax(np.where(seen[:, None], v, 0), 1) + 1
        tile_u = np.arange(tiles_x) * TILE
        tile_v = np.arange(tiles_y) * TILE
        overlap_u = (u1[None] >= tile_u[:, None]) & (u0[None] <= tile_u[:, None] + TILE)  # [tiles_x, B]
        overlap_v = (v1[None] >= tile_v[:, None]) & (v0[None] <= tile_v[:, None] + TILE)  # [tiles_y, B]
        overlap = overlap_v[:, None, :] & overlap_u[None, :, :] & seen
        overlap |= view.boxes.inside
        return overlap.reshape(tiles_y * tiles_x, -1)

    # --- shading -------------------------------------------------------------------------------

    def _shade(self, view: _View, directions, t, box, face, lighting: Lighting) -> torch.Tensor:
        """RGB ``[N, 3]`` of the hits (albedo x irradiance + emission) or of the sky."""
        boxes = view.tensors
        flat = box * 6 + face
        texture = boxes["texture"][flat]
        sky = texture == SKY
        t = torch.where(sky, torch.ones_like(t), t)
        point = boxes["center"] + t[:, None] * directions
        frame = self.frames[boxes["inside"][box].long(), face]
        normal, u_axis, v_axis = frame[:, 0], frame[:, 1], frame[:, 2]
        u_period, v_period = boxes["u_period"][flat], boxes["v_period"][flat]
        u = ((point * u_axis).sum(-1) - boxes["u_origin"][flat]) / u_period
        v = ((point * v_axis).sum(-1) - boxes["v_origin"][flat]) / v_period
        lod = self._level_of_detail(view, t, directions, normal, u_axis, v_axis, u_period, v_period)
        texel = self.atlas.sample(texture.clamp(min=0), u, v, lod)
        albedo, emission = texel[:, :3], texel[:, 3:]
        lit = (_cell_hash(u.floor(), v.floor(), box) < boxes["lit_fraction"][flat]).to(torch.float32)[:, None]
        colour = albedo * self._irradiance(point, normal, lighting) + albedo * emission * lit * lighting.emission_gain
        if sky.any():
            colour[sky] = self._sky(directions[sky], lighting, view.camera.fx * view.samples)
        return colour

    def _level_of_detail(self, view: _View, t, directions, normal, u_axis, v_axis, u_period, v_period) -> torch.Tensor:
        """Mip level from the texel footprint of one sample (ray differentials on the plane).

        One sample step changes the ray direction by ``s = R^T (1 / (f s), 0, 0)`` (or along
        ``y``); on the hit plane the point moves by ``t (s - d (n . s) / (n . d))``.
        """
        R = view.tensors["rotation"]
        steps = (R[0] / (view.camera.fx * view.samples), R[1] / (view.camera.fy * view.samples))
        n_dot_d = (normal * directions).sum(-1)
        n_dot_d = torch.where(n_dot_d.abs() < 1e-6, torch.full_like(n_dot_d, -1e-6), n_dot_d)
        lengths = []
        for step in steps:
            shift = t[:, None] * (step[None] - directions * ((normal @ step) / n_dot_d)[:, None])
            du = (shift * u_axis).sum(-1) / u_period
            dv = (shift * v_axis).sum(-1) / v_period
            lengths.append(torch.sqrt(du * du + dv * dv) * self.atlas.size)
        major, minor = torch.maximum(*lengths), torch.minimum(*lengths)
        return torch.log2(torch.maximum(major / ANISOTROPY, minor).clamp(min=1e-6))

    def _irradiance(self, point, normal, lighting: Lighting) -> torch.Tensor:
        def vector(values) -> torch.Tensor:
            return torch.tensor(values, dtype=torch.float32, device=self.device)

        irradiance = vector(lighting.ambient) * (1.0 + lighting.ambient_tilt * normal[:, 2:3])
        irradiance = (
            irradiance + vector(lighting.sun_colour) * (normal @ vector(lighting.sun_direction)).clamp(min=0.0)[:, None]
        )
        for grid in lighting.lamps:
            uniform = bool((grid.colours == grid.colours[0, 0]).all())
            colours = vector(grid.colours)  # [count, rows, 3]
            total = torch.zeros(len(point) if uniform else (len(point), 3), device=self.device)
            nearest = torch.round((point[:, 0] - grid.x0) / grid.spacing).to(torch.int64)
            for offset in (-1, 0, 1):
                column = nearest + offset
                exists = ((column >= 0) & (column < len(colours))).to(torch.float32)
                column = column.clamp(0, len(colours) - 1)
                dx = grid.x0 + column.to(torch.float32) * grid.spacing - point[:, 0]
                facing_x = normal[:, 0] * dx
                for row, (y, z) in enumerate(grid.rows):
                    dy, dz = y - point[:, 1], z - point[:, 2]
                    distance2 = dx * dx + dy * dy + dz * dz
                    cosine = (facing_x + normal[:, 1] * dy + normal[:, 2] * dz).clamp(min=0.0) * torch.rsqrt(
                        distance2 + 1e-6
                    )
                    window = (1.0 - distance2 / grid.radius**2).clamp(min=0.0)
                    weight = exists * cosine * window * window / (1.0 + distance2 / grid.reach**2)
                    total = total + (weight if uniform else weight[:, None] * colours[column, row])
            irradiance = irradiance + (total[:, None] * colours[0, 0] if uniform else total)
        return irradiance

    def _sky(self, directions, lighting: Lighting, focal: float) -> torch.Tensor:
        """Sky colour of world directions: elevation gradient and clouds on a plane at infinity."""
        unit = directions / directions.norm(dim=-1, keepdim=True)
        elevation = unit[:, 2].clamp(min=0.0)
        horizon = torch.tensor(lighting.sky_horizon, dtype=torch.float32, device=self.device)
        zenith = torch.tensor(lighting.sky_zenith, dtype=torch.float32, device=self.device)
        colour = horizon + (zenith - horizon) * torch.sqrt(elevation)[:, None]
        height = elevation.clamp(min=0.05)
        u = CLOUD_SCALE * unit[:, 0] / height
        v = CLOUD_SCALE * unit[:, 1] / height
        lod = torch.log2(CLOUD_SCALE * self.atlas.size / (focal * height * height))
        texture = torch.full_like(u, self.environment.cloud_texture, dtype=torch.int64)
        cover = self.atlas.sample(texture, u, v, lod)[:, :1] * ((elevation - 0.03) / 0.12).clamp(0.0, 1.0)[:, None]
        cloud = torch.tensor(lighting.cloud_colour, dtype=torch.float32, device=self.device)
        return colour * (1.0 - cover) + cloud * cover


def _cell_hash(u_cell: torch.Tensor, v_cell: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """Deterministic pseudo-random value in ``[0, 1)`` per (texture cell, box index)."""
    h = u_cell.to(torch.int64) * 73856093 + v_cell.to(torch.int64) * 19349663 + box * 83492791
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFF).to(torch.float32) / 65536.0
