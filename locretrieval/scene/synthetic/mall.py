"""The ``mall`` environment: a shopping-mall corridor.

A corridor ``length`` x 10 m x 5 m (``x`` along it, ``y`` in [-5, 5]): tiled floor, panelled
ceiling with rows of identical lamps, two rows of identical columns, benches and planters
down the middle, and along both walls shop fronts with unique illuminated signs (some also
with a blade sign across the corridor) and posters between the shops and on some columns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from locretrieval.scene.synthetic import textures as tx
from locretrieval.scene.synthetic.config import EnvironmentBuilder
from locretrieval.scene.synthetic.world import BoxSetBuilder, Environment, LampGrid, Lighting, Surface, TextureBank

HALF_WIDTH = 5.0
CEILING = 5.0
COLUMN_Y = 3.0
COLUMN_HALF = 0.3
COLUMN_SPACING = 8.0
LAMP_SPACING = 4.0
LAMP_ROWS = (-1.5, 1.5)
LAMP_HEIGHT = 4.82


@dataclass
class Mall(EnvironmentBuilder):
    """The shop corridor (`build_mall`)."""

    def build(self, rng: np.random.Generator, length: float, texture_size: int) -> Environment:
        return build_mall(rng, length, texture_size)


def build_mall(rng: np.random.Generator, length: float, size: int) -> Environment:
    """A random mall corridor of ``length`` metres with ``size`` x ``size`` textures."""
    bank = TextureBank()
    glyphs = tx.Glyphs(rng)
    stone = [tx.random_colour(rng, (0.0, 0.25), (0.55, 0.95)) for _ in range(3)]
    metal = bank.add(tx.metal(rng, size, (0.55, 0.56, 0.6)))
    frame = Surface(metal, period=(1.0, 1.0))
    builder = BoxSetBuilder()
    builder.add(
        [0.0, -HALF_WIDTH, 0.0],
        [length, HALF_WIDTH, CEILING],
        {
            "-z": Surface(bank.add(tx.tiles(rng, size, 4, stone, (0.35, 0.33, 0.3))), period=(2.0, 2.0)),
            "+z": Surface(bank.add(tx.perforated_panels(rng, size, 2, (0.9, 0.9, 0.87))), period=(1.2, 1.2)),
            "all": Surface(
                bank.add(tx.plaster(rng, size, tx.random_colour(rng, (0.0, 0.2), (0.7, 0.95)), 2)), period=(3.0, 3.0)
            ),
            "-x": Surface(bank.add(tx.mural(rng, glyphs, size, 2 * HALF_WIDTH / CEILING))),
            "+x": Surface(bank.add(tx.mural(rng, glyphs, size, 2 * HALF_WIDTH / CEILING))),
        },
        inside=True,
    )
    for side in (-1.0, 1.0):
        _add_shops(builder, bank, rng, glyphs, size, length, side, frame)
    _add_columns(builder, bank, rng, glyphs, size, length, frame)
    lamps = _add_lamps(builder, bank, size, length, frame)
    _add_furniture(builder, bank, rng, size, length, frame)
    clothes = [bank.add(tx.fabric(rng, size)) for _ in range(8)]
    heads = [bank.add(tx.skin(rng, size)) for _ in range(3)]
    cloud = bank.add(tx.clouds(rng, size))
    return Environment(
        name="mall",
        boxes=builder.build(),
        textures=bank.textures,
        day=_day(lamps),
        night=_night(rng, lamps),
        walk_x=(1.5, length - 1.5),
        walk_y=(-HALF_WIDTH + 0.8, HALF_WIDTH - 0.8),
        mapping_lanes=(-1.5, 1.5),
        mapping_height=1.7,
        clothes_textures=clothes,
        head_textures=heads,
        vehicle_textures=[],
        glass_texture=None,
        road_y=None,
        cloud_texture=cloud,
    )


def _wall_box(side: float, x0: float, x1: float, z0: float, z1: float, depth: float):
    """``lo, hi`` of a box on the wall at ``y = side * HALF_WIDTH`` protruding ``depth`` inwards."""
    y_wall = side * HALF_WIDTH
    y_inner = y_wall - side * depth
    return [x0, min(y_wall, y_inner), z0], [x1, max(y_wall, y_inner), z1]


def _add_shops(builder, bank, rng, glyphs, size, length, side, frame) -> None:
    visible = "+y" if side < 0 else "-y"
    x = rng.uniform(0.3, 1.5)
    while x < length - 3.0:
        width = min(rng.uniform(4.5, 7.5), length - 0.3 - x)
        front = Surface(bank.add(tx.shop_front(rng, glyphs, size, width / 3.2)))
        builder.add(*_wall_box(side, x, x + width, 0.0, 3.2, 0.1), {"all": frame, visible: front})
        sign = Surface(bank.add(tx.sign(rng, glyphs, size, (width - 0.6) / 0.8)))
        builder.add(*_wall_box(side, x + 0.3, x + width - 0.3, 3.4, 4.2, 0.25), {"all": frame, visible: sign})
        if rng.random() < 0.5:
            blade = Surface(bank.add(tx.sign(rng, glyphs, size, 0.9 / 0.6)))
            lo, hi = _wall_box(side, x + 0.4, x + 0.46, 2.9, 3.5, 1.1)
            builder.add(lo, hi, {"all": frame, "-x": blade, "+x": blade})
        gap = rng.uniform(0.7, 1.6)
        if gap > 0.95:
            centre = x + width + gap / 2
            poster = Surface(bank.add(tx.poster(rng, glyphs, size, 0.7 / 1.2, emission=0.5)))
            builder.add(*_wall_box(side, centre - 0.35, centre + 0.35, 0.9, 2.1, 0.04), {"all": frame, visible: poster})
        x += width + gap


def _add_columns(builder, bank, rng, glyphs, size, length, frame) -> None:
    """Identical columns (repeated structure); a few carry a unique poster facing along x."""
    column = Surface(
        bank.add(
            tx.marble_column(
                rng, size, 2 * COLUMN_HALF / CEILING, tx.random_colour(rng, (0.0, 0.2), (0.6, 0.9)), (0.7, 0.68, 0.6)
            )
        )
    )
    for x in np.arange(COLUMN_SPACING / 2, length - 1.0, COLUMN_SPACING):
        for y in (-COLUMN_Y, COLUMN_Y):
            builder.add([x - COLUMN_HALF, y - COLUMN_HALF, 0.0], [x + COLUMN_HALF, y + COLUMN_HALF, CEILING], column)
            if rng.random() < 0.3:
                face = "-x" if rng.random() < 0.5 else "+x"
                poster = Surface(bank.add(tx.poster(rng, glyphs, size, 0.5 / 0.8, emission=0.5)))
                x_face = x - COLUMN_HALF if face == "-x" else x + COLUMN_HALF
                x0, x1 = (x_face - 0.03, x_face) if face == "-x" else (x_face, x_face + 0.03)
                builder.add([x0, y - 0.25, 1.1], [x1, y + 0.25, 1.9], {"all": frame, face: poster})


def _add_lamps(builder, bank, size, length, frame) -> tuple[float, int]:
    """Identical ceiling lamps in rows along x; returns the first lamp's x and the lamp count per row."""
    lamp = Surface(bank.add(tx.lamp(size)))
    columns = np.arange(LAMP_SPACING / 2, length, LAMP_SPACING)
    for x in columns:
        for y in LAMP_ROWS:
            builder.add(
                [x - 0.6, y - 0.2, LAMP_HEIGHT], [x + 0.6, y + 0.2, LAMP_HEIGHT + 0.08], {"all": frame, "-z": lamp}
            )
    return float(columns[0]), len(columns)


def _add_furniture(builder, bank, rng, size, length, frame) -> None:
    """Identical benches and planters along the corridor's centre line."""
    bench = Surface(bank.add(tx.wood(rng, size, tx.random_colour(rng, (0.3, 0.6), (0.35, 0.7)), 4)), period=(1.0, 1.0))
    leaves = Surface(bank.add(tx.foliage(rng, size)), period=(1.2, 1.2))
    for k, x in enumerate(np.arange(6.0, length - 3.0, 6.0)):
        if k % 2 == 0:
            builder.add([x - 0.9, -0.25, 0.0], [x + 0.9, 0.25, 0.45], bench)
        else:
            builder.add([x - 0.6, -0.6, 0.0], [x + 0.6, 0.6, 0.7], {"all": frame, "+z": leaves})


def _lamp_grid(first: float, count: int, colours: np.ndarray, reach: float) -> LampGrid:
    rows = tuple((y, LAMP_HEIGHT - 0.2) for y in LAMP_ROWS)
    return LampGrid(first, LAMP_SPACING, rows, np.broadcast_to(colours, (count, len(rows), 3)).copy(), reach)


def _day(lamps: tuple[float, int]) -> Lighting:
    return Lighting(
        ambient=(0.62, 0.61, 0.6),
        ambient_tilt=0.12,
        sun_direction=(0.0, 0.0, 1.0),
        sun_colour=(0.0, 0.0, 0.0),
        lamps=(_lamp_grid(*lamps, np.array([0.5, 0.48, 0.42]), reach=4.0),),
        emission_gain=0.3,
        sky_horizon=(0.8, 0.8, 0.8),
        sky_zenith=(0.8, 0.8, 0.8),
        cloud_colour=(1.0, 1.0, 1.0),
    )


def _night(rng: np.random.Generator, lamps: tuple[float, int]) -> Lighting:
    """After closing: every other lamp off, the rest tinted; dim bluish ambient; glowing signs."""
    first, count = lamps
    tints = np.array([[1.0, 0.55, 0.2], [0.3, 0.7, 1.0], [0.9, 0.3, 0.8], [1.0, 0.85, 0.5]])
    colours = 2.0 * tints[rng.integers(0, len(tints), (count, len(LAMP_ROWS)))]
    colours[np.arange(count) % 2 != 0] = 0.0
    return Lighting(
        ambient=(0.08, 0.09, 0.14),
        ambient_tilt=0.0,
        sun_direction=(0.0, 0.0, 1.0),
        sun_colour=(0.0, 0.0, 0.0),
        lamps=(_lamp_grid(first, count, colours, reach=2.0),),
        emission_gain=0.9,
        sky_horizon=(0.02, 0.02, 0.04),
        sky_zenith=(0.02, 0.02, 0.04),
        cloud_colour=(0.02, 0.02, 0.04),
    )
