"""Scene description: axis-aligned textured boxes, lights and where cameras may go.

World frame: metres, ``x`` along the corridor/street, ``y`` across, ``z`` up, floor at ``z = 0``.
A box's faces are indexed ``2 * axis + side`` (side 0 = the ``lo`` face, 1 = the ``hi`` face).
A box is either solid (seen from outside) or a room (``inside``: seen from within, e.g. the
corridor's floor, walls and ceiling). Each face carries a texture mapping
``u = (p . u_axis - u_origin) / u_period``, ``v = (p . v_axis - v_origin) / v_period``
where, looking at the visible side of a vertical face, ``u_axis`` points right and
``v_axis`` down, so text on signs reads the right way round.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

SKY = -1  # texture index of faces rendered as sky (at infinity, no depth)
FACE_NAMES = ("-x", "+x", "-y", "+y", "-z", "+z")


def face_frames() -> np.ndarray:
    """``[2, 6, 3, 3]``: for (inside, face) the visible normal, ``u_axis`` and ``v_axis``."""
    frames = np.zeros((2, 6, 3, 3))
    up = np.array([0.0, 0.0, 1.0])
    for inside in (0, 1):
        for face in range(6):
            axis, side = divmod(face, 2)
            normal = np.zeros(3)
            normal[axis] = (1.0 if side else -1.0) * (-1.0 if inside else 1.0)
            u_axis = np.cross(up, normal) if axis < 2 else np.array([1.0, 0.0, 0.0])
            frames[inside, face] = (normal, u_axis, np.cross(u_axis, normal))
    return frames


FACE_FRAMES = face_frames()


@dataclass(frozen=True)
class Surface:
    """How a face is textured.

    ``period``: metres per texture repeat along ``(u, v)``, anchored at world ``anchor``
    (``u_origin, v_origin``); ``None`` stretches one copy over the face (unique panels).
    ``lit_fraction``: at night, the share of texture cells (one per period) whose emission
    is switched on, chosen by a hash of the cell (lit windows); signs use 1.
    """

    texture: int
    period: tuple[float, float] | None = None
    anchor: tuple[float, float] = (0.0, 0.0)
    lit_fraction: float = 1.0


@dataclass
class BoxSet:
    """Arrays describing ``B`` boxes; per-face arrays are ``[B, 6]``."""

    lo: np.ndarray
    hi: np.ndarray
    inside: np.ndarray
    dynamic: np.ndarray
    texture: np.ndarray
    u_origin: np.ndarray
    v_origin: np.ndarray
    u_period: np.ndarray
    v_period: np.ndarray
    lit_fraction: np.ndarray

    def __len__(self) -> int:
        return len(self.lo)

    def concat(self, other: "BoxSet") -> "BoxSet":
        return BoxSet(**{f.name: np.concatenate([getattr(self, f.name), getattr(other, f.name)]) for f in fields(self)})

    def corners(self) -> np.ndarray:
        """``[B, 8, 3]`` box corners."""
        pick = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=bool)
        return np.where(pick[None], self.hi[:, None, :], self.lo[:, None, :])

    def contains(self, points: np.ndarray, margin: float) -> np.ndarray:
        """``[N, B]``: point ``n`` lies within ``margin`` of solid box ``b`` (rooms excluded)."""
        points = np.asarray(points, dtype=np.float64)[:, None, :]
        near = ((points > self.lo - margin) & (points < self.hi + margin)).all(-1)
        return near & ~self.inside[None]


@dataclass
class BoxSetBuilder:
    """Collects boxes with per-face :class:`Surface` s and produces a :class:`BoxSet`."""

    rows: list[tuple] = field(default_factory=list)

    def add(self, lo, hi, surfaces: Surface | dict[str, Surface], inside: bool = False, dynamic: bool = False) -> None:
        """Add a box; ``surfaces`` is one surface for all faces or a dict keyed by
        :data:`FACE_NAMES` with an optional ``"all"`` default."""
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        if not (hi > lo).all():
            raise ValueError(f"box with lo={lo} hi={hi} is empty")
        if isinstance(surfaces, Surface):
            surfaces = {"all": surfaces}
        unknown = set(surfaces) - set(FACE_NAMES) - {"all"}
        if unknown:
            raise ValueError(f"unknown face names {sorted(unknown)}; use {FACE_NAMES} or 'all'")
        per_face = []
        for face, name in enumerate(FACE_NAMES):
            surface = surfaces.get(name, surfaces.get("all"))
            if surface is None:
                raise ValueError(f"no surface given for face {name} of box lo={lo} hi={hi}")
            per_face.append(self._mapping(lo, hi, face, inside, surface))
        self.rows.append((lo, hi, inside, dynamic, per_face))

    @staticmethod
    def _mapping(lo: np.ndarray, hi: np.ndarray, face: int, inside: bool, surface: Surface) -> tuple:
        _, u_axis, v_axis = FACE_FRAMES[int(inside), face]
        if surface.period is None:
            u_origin, v_origin = min(u_axis @ lo, u_axis @ hi), min(v_axis @ lo, v_axis @ hi)
            u_period, v_period = abs(u_axis @ (hi - lo)), abs(v_axis @ (hi - lo))
        else:
            (u_origin, v_origin), (u_period, v_period) = surface.anchor, surface.period
        return surface.texture, u_origin, v_origin, u_period, v_period, surface.lit_fraction

    def build(self) -> BoxSet:
        if not self.rows:
            return empty_box_set()
        faces = np.array([[list(m) for m in row[4]] for row in self.rows], dtype=np.float64)  # [B, 6, 6]
        return BoxSet(
            lo=np.stack([row[0] for row in self.rows]),
            hi=np.stack([row[1] for row in self.rows]),
            inside=np.array([row[2] for row in self.rows], dtype=bool),
            dynamic=np.array([row[3] for row in self.rows], dtype=bool),
            texture=faces[..., 0].astype(np.int64),
            u_origin=faces[..., 1],
            v_origin=faces[..., 2],
            u_period=faces[..., 3],
            v_period=faces[..., 4],
            lit_fraction=faces[..., 5],
        )


def empty_box_set() -> BoxSet:
    per_face = np.zeros((0, 6))
    return BoxSet(
        np.zeros((0, 3)),
        np.zeros((0, 3)),
        np.zeros(0, bool),
        np.zeros(0, bool),
        per_face.astype(np.int64),
        per_face,
        per_face,
        per_face,
        per_face,
        per_face,
    )


class TextureBank:
    """Textures of a scene in the order of their indices."""

    def __init__(self) -> None:
        self.textures: list[np.ndarray] = []

    def add(self, texture: np.ndarray) -> int:
        self.textures.append(texture)
        return len(self.textures) - 1


@dataclass(frozen=True)
class LampGrid:
    """Point lamps at ``x = x0 + k * spacing`` (``k < count``) and ``(y, z)`` in ``rows``.

    ``colours [count, len(rows), 3]`` (zero for lamps that are off). A lamp at distance ``d``
    lights a surface with ``colour * max(0, cos) / (1 + d^2 / reach^2) * max(0, 1 - d^2 / radius^2)^2``;
    the window makes it exactly zero beyond ``radius = 1.5 * spacing``, so only the three
    nearest lamp columns of a point contribute.
    """

    x0: float
    spacing: float
    rows: tuple[tuple[float, float], ...]
    colours: np.ndarray
    reach: float

    @property
    def radius(self) -> float:
        return 1.5 * self.spacing


@dataclass(frozen=True)
class Lighting:
    """Illumination of one condition; colours are RGB multipliers of albedo.

    Irradiance at a surface point with normal ``n``: ``ambient * (1 + ambient_tilt * n_z)``
    + sun (``sun_colour * max(0, n . sun_direction)``, direction towards the sun)
    + lamps (:class:`LampGrid`), no shadows. Emissive texels add
    ``albedo * emission * emission_gain``. The sky blends ``sky_horizon`` to ``sky_zenith``
    with elevation, plus ``cloud_colour`` where cloudy.
    """

    ambient: tuple[float, float, float]
    ambient_tilt: float
    sun_direction: tuple[float, float, float]
    sun_colour: tuple[float, float, float]
    lamps: tuple[LampGrid, ...]
    emission_gain: float
    sky_horizon: tuple[float, float, float]
    sky_zenith: tuple[float, float, float]
    cloud_colour: tuple[float, float, float]


@dataclass
class Environment:
    """A built scene: static boxes, textures, lighting per condition and camera placement.

    Cameras walk inside ``walk_x`` x ``walk_y`` (metres); mapping passes run along ``x`` at
    the lateral offsets ``mapping_lanes`` and height ``mapping_height``. Dynamic objects are
    textured with the indices listed here (people: clothes and heads; vehicles: bodies and
    glass) and vehicles stay on the road (``road_y``; ``None`` where there is none).
    ``cloud_texture`` is the cloud cover sampled by sky faces.
    """

    name: str
    boxes: BoxSet
    textures: list[np.ndarray]
    day: Lighting
    night: Lighting
    walk_x: tuple[float, float]
    walk_y: tuple[float, float]
    mapping_lanes: tuple[float, ...]
    mapping_height: float
    clothes_textures: list[int]
    head_textures: list[int]
    vehicle_textures: list[int]
    glass_texture: int | None
    road_y: tuple[float, float] | None
    cloud_texture: int
