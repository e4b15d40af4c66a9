"""The ``street`` environment: an urban street between two rows of buildings.

A road (``y`` in [-4, 4]) with raised sidewalks up to ``|y| = 8`` runs along ``x`` for
``length`` metres, closed at both ends by cross buildings. Buildings have varied widths and
heights; facades repeat one window module per building (styles shared between some
buildings), and the ground floors carry unique shop fronts, signs, doors and graffiti.
Identical street lamps stand along both kerbs. Above the roofs is sky (at infinity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from locretrieval.scene.synthetic import textures as tx
from locretrieval.scene.synthetic.config import EnvironmentBuilder
from locretrieval.scene.synthetic.world import SKY, BoxSetBuilder, Environment, LampGrid, Lighting, Surface, TextureBank

ROAD_HALF = 4.0
FACADE_Y = 8.0
KERB = 0.15
DEPTH = 10.0
LAMP_SPACING = 12.0
LAMP_Y = 4.5
LAMP_HEIGHT = 5.5
MODULE = (3.2, 3.2)  # facade window module, metres
GROUND_FLOOR = 4.2
LIT_WINDOWS = 0.4  # share of windows lit at night


@dataclass
class Street(EnvironmentBuilder):
    """The street of facades, road and sky (`build_street`)."""

    def build(self, rng: np.random.Generator, length: float, texture_size: int) -> Environment:
        return build_street(rng, length, texture_size)


def build_street(rng: np.random.Generator, length: float, size: int) -> Environment:
    """A random street of ``length`` metres with ``size`` x ``size`` textures."""
    bank = TextureBank()
    glyphs = tx.Glyphs(rng)
    metal = Surface(bank.add(tx.metal(rng, size, (0.3, 0.31, 0.33))), period=(1.0, 1.0))
    concrete = Surface(bank.add(tx.plaster(rng, size, (0.62, 0.61, 0.58), 1)), period=(2.0, 2.0))
    styles = [bank.add(tx.facade_module(rng, size)) for _ in range(max(3, int(length // 16)))]
    builder = BoxSetBuilder()
    far = length + 2 * DEPTH
    builder.add(
        [-DEPTH - 2.0, -FACADE_Y - DEPTH - 2.0, 0.0],
        [far, FACADE_Y + DEPTH + 2.0, 80.0],
        {
            "all": Surface(SKY),
            "-z": Surface(
                bank.add(tx.asphalt_road(rng, size, 0.5)), period=(6.0, 2 * ROAD_HALF), anchor=(0.0, -ROAD_HALF)
            ),
        },
        inside=True,
    )
    paving = Surface(
        bank.add(tx.tiles(rng, size, 4, [(0.62, 0.6, 0.56), (0.55, 0.54, 0.52), (0.66, 0.62, 0.55)], (0.4, 0.4, 0.38))),
        period=(2.0, 2.0),
    )
    for side in (-1.0, 1.0):
        y0, y1 = sorted((side * ROAD_HALF, side * FACADE_Y))
        builder.add([0.0, y0, 0.0], [length, y1, KERB], {"all": concrete, "+z": paving})
        _add_buildings(builder, bank, rng, glyphs, size, length, side, styles, concrete)
    for x_face, face in ((0.0, "+x"), (length, "-x")):
        x0, x1 = (x_face - DEPTH, x_face) if face == "+x" else (x_face, x_face + DEPTH)
        facade = Surface(int(rng.choice(styles)), period=MODULE, anchor=(0.0, -16.0), lit_fraction=LIT_WINDOWS)
        builder.add([x0, -FACADE_Y - DEPTH, 0.0], [x1, FACADE_Y + DEPTH, 16.0], {"all": concrete, face: facade})
        mural = Surface(bank.add(tx.mural(rng, glyphs, size, 8.0 / 3.5)))
        mural_x = (x_face, x_face + 0.03) if face == "+x" else (x_face - 0.03, x_face)
        builder.add([mural_x[0], -4.0, 0.5], [mural_x[1], 4.0, 4.0], {"all": concrete, face: mural})
    lamps = _add_lamps(builder, bank, size, length, metal)
    clothes = [bank.add(tx.fabric(rng, size)) for _ in range(8)]
    heads = [bank.add(tx.skin(rng, size)) for _ in range(3)]
    bodies = [bank.add(tx.car_body(rng, size, 4.2 / 0.95)) for _ in range(5)]
    return Environment(
        name="street",
        boxes=builder.build(),
        textures=bank.textures,
        day=_day(),
        night=_night(lamps),
        walk_x=(2.0, length - 2.0),
        walk_y=(-FACADE_Y + 0.8, FACADE_Y - 0.8),
        mapping_lanes=(-2.0, 2.0),
        mapping_height=2.2,
        clothes_textures=clothes,
        head_textures=heads,
        vehicle_textures=bodies,
        glass_texture=bank.add(tx.tinted_glass(size)),
        road_y=(-ROAD_HALF + 1.2, ROAD_HALF - 1.2),
        cloud_texture=bank.add(tx.clouds(rng, size)),
    )


def _facade_box(side: float, x0: float, x1: float, z0: float, z1: float, depth: float, out: float = 0.0):
    """``lo, hi`` of a slab on the facade plane ``|y| = FACADE_Y`` protruding ``depth`` towards the road."""
    y_face = side * (FACADE_Y + out)
    y_front = side * (FACADE_Y - depth)
    return [x0, min(y_face, y_front), z0], [x1, max(y_face, y_front), z1]


def _add_buildings(builder, bank, rng, glyphs, size, length, side, styles, concrete) -> None:
    visible = "+y" if side < 0 else "-y"
    x = 0.0
    while x < length - 0.5:
        width = min(rng.uniform(7.0, 13.0), length - x)
        if length - (x + width) < 4.0:
            width = length - x
        height = GROUND_FLOOR + MODULE[1] * rng.integers(1, 6)
        style = Surface(
            int(rng.choice(styles)),
            period=MODULE,
            anchor=(float(rng.uniform(0, MODULE[0])), -height),
            lit_fraction=LIT_WINDOWS,
        )
        builder.add(*_facade_box(side, x, x + width, 0.0, height, 0.0, out=DEPTH), {"all": style, "+z": concrete})
        _add_ground_floor(builder, bank, rng, glyphs, size, side, visible, x, width, concrete)
        x += width


def _add_ground_floor(builder, bank, rng, glyphs, size, side, visible, x, width, concrete) -> None:
    """Unique shop front with a sign (and maybe a blade sign), a door and maybe graffiti."""
    front = rng.uniform(0.45, 0.65) * width
    start = x + (0.4 if rng.random() < 0.5 else width - 0.4 - front)
    shop = Surface(bank.add(tx.shop_front(rng, glyphs, size, front / 3.3)))
    builder.add(*_facade_box(side, start, start + front, KERB, KERB + 3.3, 0.12), {"all": concrete, visible: shop})
    sign = Surface(bank.add(tx.sign(rng, glyphs, size, (front - 0.4) / 0.8)))
    builder.add(*_facade_box(side, start + 0.2, start + front - 0.2, 3.6, 4.4, 0.2), {"all": concrete, visible: sign})
    if rng.random() < 0.5:
        blade = Surface(bank.add(tx.sign(rng, glyphs, size, 0.9 / 0.7)))
        edge = start + front - 0.3
        builder.add(*_facade_box(side, edge, edge + 0.06, 4.6, 5.3, 1.1), {"all": concrete, "-x": blade, "+x": blade})
    free = (x + 0.3, start - 0.3) if start - x > width / 2 - front / 2 else (start + front + 0.3, x + width - 0.3)
    if free[1] - free[0] > 1.4:
        door_x = free[0] + rng.uniform(0.0, free[1] - free[0] - 1.3)
        door = Surface(bank.add(tx.door(rng, glyphs, size, 1.2 / 2.4)))
        builder.add(*_facade_box(side, door_x, door_x + 1.2, KERB, KERB + 2.4, 0.06), {"all": concrete, visible: door})
        rest = (door_x + 1.5, free[1]) if free[1] - door_x - 1.5 > door_x - free[0] else (free[0], door_x - 0.3)
        if rest[1] - rest[0] > 1.2 and rng.random() < 0.7:
            patch_width = min(rest[1] - rest[0], rng.uniform(1.2, 3.0))
            paint = Surface(bank.add(tx.graffiti(rng, glyphs, size, patch_width / 1.6)))
            builder.add(
                *_facade_box(side, rest[0], rest[0] + patch_width, 0.5, 2.1, 0.02), {"all": concrete, visible: paint}
            )


def _add_lamps(builder, bank, size, length, metal) -> tuple[float, int]:
    """Identical lamp posts on both kerbs; returns the first post's x and the post count."""
    head = Surface(bank.add(tx.lamp(size)))
    columns = np.arange(LAMP_SPACING / 2, length, LAMP_SPACING)
    for x in columns:
        for side in (-1.0, 1.0):
            y = side * LAMP_Y
            builder.add([x - 0.08, y - 0.08, KERB], [x + 0.08, y + 0.08, LAMP_HEIGHT + 0.2], metal)
            arm = sorted((y, y - side * 1.0))
            builder.add(
                [x - 0.15, arm[0], LAMP_HEIGHT], [x + 0.15, arm[1], LAMP_HEIGHT + 0.15], {"all": metal, "-z": head}
            )
    return float(columns[0]), len(columns)


def _lamp_grid(lamps: tuple[float, int], colour, reach: float) -> LampGrid:
    first, count = lamps
    rows = tuple((side * (LAMP_Y - 0.6), LAMP_HEIGHT - 0.1) for side in (-1.0, 1.0))
    return LampGrid(first, LAMP_SPACING, rows, np.broadcast_to(np.asarray(colour, float), (count, 2, 3)).copy(), reach)


def _day() -> Lighting:
    sun = np.array([0.45, -0.55, 0.7])
    return Lighting(
        ambient=(0.5, 0.52, 0.58),
        ambient_tilt=0.25,
        sun_direction=tuple(sun / np.linalg.norm(sun)),
        sun_colour=(0.55, 0.52, 0.45),
        lamps=(),
        emission_gain=0.1,
        sky_horizon=(0.78, 0.84, 0.92),
        sky_zenith=(0.32, 0.52, 0.85),
        cloud_colour=(0.96, 0.96, 0.97),
    )


def _night(lamps: tuple[float, int]) -> Lighting:
    """Sodium street lamps with a short reach, lit windows and signs, a dark sky."""
    return Lighting(
        ambient=(0.03, 0.035, 0.06),
        ambient_tilt=0.0,
        sun_direction=(0.0, 0.0, 1.0),
        sun_colour=(0.0, 0.0, 0.0),
        lamps=(_lamp_grid(lamps, (3.2, 1.8, 0.7), reach=3.0),),
        emission_gain=1.0,
        sky_horizon=(0.07, 0.07, 0.13),
        sky_zenith=(0.01, 0.01, 0.04),
        cloud_colour=(0.09, 0.08, 0.1),
    )
