"""Procedural textures: tileable noise octaves, shapes, glyph text and logos.

Every texture is a float32 array ``[S, S, 4]``: RGB albedo in ``[0, 1]`` and an emission
weight in the fourth channel (shop signs, lit windows, lamps). Panel textures are painted on
a canvas with the aspect ratio of the surface they cover and resampled to ``S x S``, so they
look undistorted once stretched over that surface. Shapes are drawn at twice the canvas
resolution and box-filtered down, which anti-aliases their edges.
"""

from __future__ import annotations

import colorsys
import math

import numpy as np
from PIL import Image, ImageDraw

Colour = tuple[float, float, float]


# --- colours and noise -------------------------------------------------------------------------


def random_colour(rng: np.random.Generator, saturation=(0.5, 1.0), value=(0.5, 1.0), hue=None) -> Colour:
    """An RGB colour in ``[0, 1]`` from random HSV ranges."""
    h = rng.random() if hue is None else hue
    return colorsys.hsv_to_rgb(h, rng.uniform(*saturation), rng.uniform(*value))


def contrasting(colour: Colour) -> Colour:
    """Near-white or near-black, whichever reads better on ``colour``."""
    luma = 0.3 * colour[0] + 0.59 * colour[1] + 0.11 * colour[2]
    return (0.08, 0.08, 0.1) if luma > 0.55 else (0.97, 0.96, 0.92)


def to_255(colour: Colour) -> tuple[int, int, int]:
    return tuple(int(round(255 * min(max(c, 0.0), 1.0))) for c in colour)  # type: ignore[return-value]


def fbm(rng: np.random.Generator, size: int, cells: int, octaves: int, persistence: float = 0.5) -> np.ndarray:
    """Tileable fractal noise ``[size, size]`` normalised to ``[0, 1]``.

    Synthesised in the frequency domain: random phases with a power-law amplitude that
    loses a factor ``persistence`` per octave, for frequencies from ``cells`` to
    ``cells * 2^octaves`` cycles per texture (capped at the Nyquist frequency).
    """
    fy = np.abs(np.fft.fftfreq(size) * size)[:, None]
    fx = (np.fft.rfftfreq(size) * size)[None, :]
    frequency = np.sqrt(fx * fx + fy * fy)
    band = (frequency >= cells * 0.75) & (frequency <= min(cells * 2.0**octaves, size / 2))
    amplitude = np.where(band, np.maximum(frequency, 1.0) ** (np.log2(persistence) - 1.0), 0.0)
    phases = rng.standard_normal((2, size, size // 2 + 1))
    noise = np.fft.irfft2(amplitude * (phases[0] + 1j * phases[1]), s=(size, size))
    return ((noise - noise.min()) / max(float(noise.max() - noise.min()), 1e-12)).astype(np.float32)


def mix(a: Colour, b: Colour, weight: np.ndarray) -> np.ndarray:
    """Per-texel blend ``[..., 3]`` of two colours by ``weight`` in ``[0, 1]``."""
    w = np.asarray(weight, dtype=np.float32)[..., None]
    a, b = np.asarray(a, dtype=np.float32), np.asarray(b, dtype=np.float32)
    return a + (b - a) * w


def rgbe(rgb: np.ndarray, emission: np.ndarray | float = 0.0) -> np.ndarray:
    """Stack RGB ``[S, S, 3]`` and emission into a float32 ``[S, S, 4]`` texture."""
    emission = np.broadcast_to(np.asarray(emission, dtype=np.float64), rgb.shape[:2])
    return np.clip(np.concatenate([rgb, emission[..., None]], axis=-1), 0.0, 1.0).astype(np.float32)


# --- glyphs, logos and a drawing canvas --------------------------------------------------------


class Glyphs:
    """A random alphabet: each glyph is 1-3 strokes through points of a 3x4 lattice."""

    def __init__(self, rng: np.random.Generator, count: int = 40):
        lattice = [(x / 2.0, y / 3.0) for x in range(3) for y in range(4)]
        self.strokes = []
        for _ in range(count):
            glyph = []
            for _ in range(rng.integers(1, 4)):
                points = rng.choice(len(lattice), size=rng.integers(2, 4), replace=False)
                glyph.append([lattice[i] for i in points])
            self.strokes.append(glyph)

    def word(self, rng: np.random.Generator, low: int, high: int) -> list[int]:
        return list(rng.integers(0, len(self.strokes), size=rng.integers(low, high + 1)))


class Canvas:
    """A PIL RGB + emission canvas for one texture, drawn at 2x and box-filtered to size."""

    def __init__(self, size: int, aspect: float, background: np.ndarray | Colour, emission: float = 0.0):
        """``aspect`` is width / height of the surface; the longer side gets ``2 * size`` pixels."""
        scale = 2 * size
        self.size = size
        self.w = scale if aspect >= 1 else max(8, int(round(scale * aspect)))
        self.h = scale if aspect < 1 else max(8, int(round(scale / aspect)))
        if isinstance(background, np.ndarray):
            self.image = Image.fromarray(np.uint8(np.clip(background, 0, 1) * 255 + 0.5)).resize(
                (self.w, self.h), Image.BILINEAR
            )
        else:
            self.image = Image.new("RGB", (self.w, self.h), to_255(background))
        self.emission = Image.new("L", (self.w, self.h), int(round(255 * emission)))
        self.draw = ImageDraw.Draw(self.image)
        self.draw_emission = ImageDraw.Draw(self.emission)

    def px(self, x: float, y: float) -> tuple[float, float]:
        """Canvas pixel of fractional coordinates ``(x, y)`` in ``[0, 1]``."""
        return x * self.w, y * self.h

    def rect(
        self, box, colour: Colour, emission: float | None = None, outline: Colour | None = None, width: float = 0.0
    ) -> None:
        x0, y0, x1, y1 = box
        corners = [*self.px(x0, y0), *self.px(x1, y1)]
        line = max(1, int(round(width * self.h))) if outline else 0
        self.draw.rectangle(corners, fill=to_255(colour), outline=to_255(outline) if outline else None, width=line)
        if emission is not None:
            self.draw_emission.rectangle(corners, fill=int(round(255 * emission)))

    def ellipse(self, box, colour: Colour, emission: float | None = None) -> None:
        x0, y0, x1, y1 = box
        corners = [*self.px(x0, y0), *self.px(x1, y1)]
        self.draw.ellipse(corners, fill=to_255(colour))
        if emission is not None:
            self.draw_emission.ellipse(corners, fill=int(round(255 * emission)))

    def polygon(self, points, colour: Colour) -> None:
        self.draw.polygon([self.px(x, y) for x, y in points], fill=to_255(colour))

    def line(self, points, colour: Colour, width: float) -> None:
        """Polyline through fractional points, ``width`` a fraction of the canvas height."""
        self.draw.line(
            [self.px(x, y) for x, y in points],
            fill=to_255(colour),
            width=max(1, int(round(width * self.h))),
            joint="curve",
        )

    def text(self, glyphs: Glyphs, word: list[int], box, colour: Colour, weight: float = 0.14) -> None:
        """Glyph string fitted into ``box`` (fractions), stroke width ``weight`` of a glyph's height."""
        x0, y0, x1, y1 = box
        height_px = (y1 - y0) * self.h
        advance = min((x1 - x0) * self.w / len(word), height_px * 0.8)
        stroke = max(1, int(round(weight * height_px)))
        left = x0 * self.w + ((x1 - x0) * self.w - advance * len(word)) / 2
        for i, index in enumerate(word):
            gx = left + i * advance + 0.15 * advance
            for points in glyphs.strokes[index]:
                xy = [(gx + 0.7 * advance * px, y0 * self.h + py * height_px) for px, py in points]
                self.draw.line(xy, fill=to_255(colour), width=stroke, joint="curve")

    def logo(self, rng: np.random.Generator, box, palette: list[Colour]) -> None:
        """A random emblem: nested discs, rings, regular polygons and stars."""
        x0, y0, x1, y1 = box
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        rx, ry = (x1 - x0) / 2, (y1 - y0) / 2
        for layer in range(rng.integers(2, 5)):
            scale = 1.0 - 0.25 * layer
            colour = palette[layer % len(palette)]
            kind = rng.integers(0, 3)
            if kind == 0:
                self.ellipse((cx - rx * scale, cy - ry * scale, cx + rx * scale, cy + ry * scale), colour)
            else:
                corners = int(rng.integers(3, 8))
                phase = rng.random() * math.tau
                radii = [1.0, 0.45] if kind == 2 else [1.0]
                n = corners * len(radii)
                points = [
                    (
                        cx + rx * scale * radii[k % len(radii)] * math.cos(phase + math.tau * k / n),
                        cy + ry * scale * radii[k % len(radii)] * math.sin(phase + math.tau * k / n),
                    )
                    for k in range(n)
                ]
                self.polygon(points, colour)

    def result(self) -> np.ndarray:
        """The canvas box-filtered to ``[S, S, 4]`` float32 (RGB + emission)."""
        rgb = np.asarray(self.image.resize((self.size, self.size), Image.BOX), dtype=np.float32) / 255.0
        emission = np.asarray(self.emission.resize((self.size, self.size), Image.BOX), dtype=np.float32) / 255.0
        return rgbe(rgb, emission)


def grain(rng: np.random.Generator, texture: np.ndarray, strength: float, cells: int = 8) -> np.ndarray:
    """Multiply RGB by tileable multi-octave noise (dirt, print grain) of relative ``strength``."""
    size = texture.shape[0]
    noise = fbm(rng, size, cells, octaves=6, persistence=0.6)
    out = texture.copy()
    out[..., :3] *= (1.0 - strength) + 2.0 * strength * noise[..., None]
    return np.clip(out, 0.0, 1.0)


# --- texture kinds -----------------------------------------------------------------------------


def tiles(rng: np.random.Generator, size: int, count: int, palette: list[Colour], grout: Colour) -> np.ndarray:
    """``count x count`` marble-like floor tiles with grout lines (tileable)."""
    cell = size // count
    choice = rng.integers(0, len(palette), size=(count, count))
    colours = np.asarray(palette)[choice]
    base = np.repeat(np.repeat(colours, cell, 0), cell, 1)
    veins = np.abs(np.sin(12.0 * fbm(rng, size, 4, 5) + 6.0 * fbm(rng, size, 2, 3)))
    rgb = base * (0.8 + 0.2 * veins[..., None]) * (0.9 + 0.2 * fbm(rng, size, 16, 3)[..., None])
    y, x = np.mgrid[0:size, 0:size] % cell
    line = max(1, cell // 24)
    joints = (x < line) | (y < line)
    rgb[joints] = grout
    return rgbe(rgb)


def perforated_panels(rng: np.random.Generator, size: int, count: int, colour: Colour) -> np.ndarray:
    """Ceiling panels with a frame grid and a regular pattern of holes (tileable)."""
    rgb = mix(colour, tuple(c * 0.92 for c in colour), fbm(rng, size, 4, 4))
    y, x = np.mgrid[0:size, 0:size]
    cell = size // count
    holes = ((x % (cell // 8) - cell // 16) ** 2 + (y % (cell // 8) - cell // 16) ** 2) < (cell / 48) ** 2
    rgb[holes] *= 0.55
    frame = (x % cell < max(2, cell // 20)) | (y % cell < max(2, cell // 20))
    rgb[frame] = (0.55, 0.56, 0.58)
    return rgbe(rgb)


def plaster(rng: np.random.Generator, size: int, colour: Colour, seams: int) -> np.ndarray:
    """Painted plaster with stains and vertical panel seams (tileable)."""
    rgb = mix(colour, tuple(c * 0.78 for c in colour), fbm(rng, size, 3, 7, 0.55) ** 1.5)
    x = np.arange(size)
    rgb[:, x % (size // seams) < max(1, size // 200)] *= 0.7
    return rgbe(rgb)


def marble_column(rng: np.random.Generator, size: int, aspect: float, colour: Colour, band: Colour) -> np.ndarray:
    """A column face: marble with metal bands and a plinth (one copy per face)."""
    background = mix(colour, tuple(c * 0.7 for c in colour), np.abs(np.sin(10.0 * fbm(rng, size, 3, 5))))
    canvas = Canvas(size, aspect, background)
    for top in (0.12, 0.45):
        canvas.rect((0.0, top, 1.0, top + 0.025), band)
        canvas.rect((0.0, top + 0.008, 1.0, top + 0.012), tuple(c * 0.6 for c in band))
    canvas.rect((0.0, 0.93, 1.0, 1.0), tuple(c * 0.5 for c in colour))
    return grain(rng, canvas.result(), 0.1)


def lamp(size: int) -> np.ndarray:
    """A light panel: bright emissive diffuser in a grey frame."""
    canvas = Canvas(size, 3.0, (0.5, 0.5, 0.52))
    canvas.rect((0.06, 0.15, 0.94, 0.85), (1.0, 0.98, 0.92), emission=1.0)
    for k in range(1, 6):
        canvas.rect((k / 6 - 0.004, 0.15, k / 6 + 0.004, 0.85), (0.8, 0.8, 0.8))
    return canvas.result()


def wood(rng: np.random.Generator, size: int, colour: Colour, planks: int) -> np.ndarray:
    """Wooden planks with grain (tileable)."""
    y, x = np.mgrid[0:size, 0:size] / size
    rings = np.sin(80.0 * y + 8.0 * fbm(rng, size, 4, 5)) * 0.5 + 0.5
    rgb = mix(colour, tuple(c * 0.65 for c in colour), rings)
    rgb[(y * planks) % 1.0 < 0.04] *= 0.4
    return rgbe(rgb)


def foliage(rng: np.random.Generator, size: int) -> np.ndarray:
    """Planter top: leaves as thresholded noise blobs over soil (tileable)."""
    leaves = fbm(rng, size, 8, 5)
    rgb = mix((0.3, 0.2, 0.12), (0.15, 0.5, 0.15), (leaves > 0.45).astype(float))
    rgb *= (0.6 + 0.6 * fbm(rng, size, 32, 2))[..., None]
    return rgbe(rgb)


def shop_front(rng: np.random.Generator, glyphs: Glyphs, size: int, aspect: float) -> np.ndarray:
    """A glazed shop front: frame, lit display with shelves and products, a door and decals."""
    frame = random_colour(rng, (0.0, 0.5), (0.15, 0.8))
    interior = random_colour(rng, (0.1, 0.5), (0.55, 0.95))
    canvas = Canvas(size, aspect, frame)
    canvas.rect((0.02, 0.05, 0.98, 0.97), interior, emission=0.7)
    for shelf in np.linspace(0.25, 0.85, rng.integers(2, 5)):
        canvas.rect((0.03, shelf, 0.97, shelf + 0.015), tuple(c * 0.5 for c in interior))
        x = 0.04
        while x < 0.92:
            width = rng.uniform(0.02, 0.07)
            height = rng.uniform(0.05, 0.14)
            box = (x, shelf - height, x + width, shelf)
            colour = random_colour(rng, (0.3, 1.0), (0.3, 1.0))
            (canvas.ellipse if rng.random() < 0.3 else canvas.rect)(box, colour)
            x += width + rng.uniform(0.005, 0.04)
    door = rng.uniform(0.1, 0.75)
    canvas.rect(
        (door, 0.15, door + 0.16, 0.97), tuple(c * 0.35 for c in interior), emission=0.2, outline=frame, width=0.02
    )
    canvas.rect((door + 0.12, 0.5, door + 0.135, 0.65), (0.85, 0.85, 0.8))
    for x in np.linspace(0.0, 1.0, rng.integers(3, 7)):
        canvas.rect((x - 0.006, 0.05, x + 0.006, 0.97), frame)
    canvas.text(glyphs, glyphs.word(rng, 5, 10), (0.05, 0.9, 0.45, 0.95), contrasting(interior), weight=0.18)
    return grain(rng, canvas.result(), 0.08)


def sign(rng: np.random.Generator, glyphs: Glyphs, size: int, aspect: float) -> np.ndarray:
    """An illuminated shop sign: coloured panel, border, logo and a glyph name."""
    base = random_colour(rng, (0.4, 1.0), (0.25, 1.0))
    ink = contrasting(base) if rng.random() < 0.6 else random_colour(rng, (0.6, 1.0), (0.7, 1.0))
    background = mix(base, tuple(c * 0.7 for c in base), fbm(rng, size, 1, 2)) if rng.random() < 0.5 else base
    canvas = Canvas(size, aspect, background, emission=1.0)
    canvas.rect((0.0, 0.0, 1.0, 1.0), base, outline=ink, width=0.06)
    logo_width = 0.8 / aspect
    canvas.logo(rng, (0.03, 0.1, 0.03 + logo_width, 0.9), [ink, random_colour(rng), base])
    left = 0.06 + logo_width
    if rng.random() < 0.5:
        canvas.text(glyphs, glyphs.word(rng, 3, 8), (left, 0.15, 0.97, 0.65), ink, weight=0.16)
        canvas.text(glyphs, glyphs.word(rng, 8, 16), (left, 0.7, 0.97, 0.88), ink, weight=0.2)
    else:
        canvas.text(glyphs, glyphs.word(rng, 3, 9), (left, 0.2, 0.97, 0.8), ink, weight=0.15)
    return grain(rng, canvas.result(), 0.05)


def poster(rng: np.random.Generator, glyphs: Glyphs, size: int, aspect: float, emission: float) -> np.ndarray:
    """An advertising poster: gradient, bold shapes, a headline and lines of small text."""
    top, bottom = random_colour(rng), random_colour(rng)
    gradient = np.linspace(0.0, 1.0, size)[:, None] * np.ones((1, size))
    canvas = Canvas(size, aspect, mix(top, bottom, gradient), emission=emission)
    for _ in range(rng.integers(3, 9)):
        x, y = rng.uniform(0.0, 1.0, 2)
        r = rng.uniform(0.05, 0.3)
        colour = random_colour(rng, (0.2, 1.0), (0.2, 1.0))
        if rng.random() < 0.5:
            canvas.ellipse((x - r, y - r * aspect, x + r, y + r * aspect), colour)
        else:
            angles = np.sort(rng.uniform(0, math.tau, rng.integers(3, 6)))
            canvas.polygon([(x + r * math.cos(a), y + r * aspect * math.sin(a)) for a in angles], colour)
    ink = random_colour(rng, (0.0, 1.0), (0.0, 1.0))
    canvas.text(glyphs, glyphs.word(rng, 3, 7), (0.08, 0.06, 0.92, 0.16), ink, weight=0.16)
    for row in np.linspace(0.72, 0.9, rng.integers(2, 5)):
        canvas.text(glyphs, glyphs.word(rng, 8, 14), (0.1, row, 0.9, row + 0.035), ink, weight=0.2)
    canvas.logo(rng, (0.78, 0.9, 0.95, 0.9 + 0.17 * aspect), [random_colour(rng), ink])
    return grain(rng, canvas.result(), 0.06)


def mural(rng: np.random.Generator, glyphs: Glyphs, size: int, aspect: float) -> np.ndarray:
    """A large wall mural: bands of colour, emblems and giant lettering."""
    colours = [random_colour(rng, (0.3, 0.9), (0.4, 1.0)) for _ in range(3)]
    y = np.linspace(0.0, 1.0, size)[:, None] * np.ones((1, size))
    canvas = Canvas(
        size, aspect, mix(colours[0], colours[1], (np.sin(6 * y + 4 * fbm(rng, size, 2, 3)) > 0).astype(float))
    )
    for _ in range(rng.integers(3, 7)):
        x0, y0 = rng.uniform(0.0, 0.8), rng.uniform(0.0, 0.7)
        canvas.logo(rng, (x0, y0, x0 + 0.15, y0 + 0.15 * aspect), [random_colour(rng), colours[2], random_colour(rng)])
    canvas.text(glyphs, glyphs.word(rng, 4, 8), (0.1, 0.55, 0.9, 0.8), colours[2], weight=0.12)
    return grain(rng, canvas.result(), 0.1)


def facade_module(rng: np.random.Generator, size: int) -> np.ndarray:
    """One repeated facade module (tileable): brick or render wall around a window."""
    wall = random_colour(rng, (0.1, 0.6), (0.35, 0.9))
    y, x = np.mgrid[0:size, 0:size]
    if rng.random() < 0.5:
        course = size // 24
        offset = (y // course % 2) * (course * 2)
        mortar = (y % course < max(1, course // 5)) | ((x + offset) % (course * 4) < max(1, course // 5))
        rgb = mix(wall, tuple(c * 0.8 for c in wall), fbm(rng, size, 16, 3))
        rgb[mortar] = (0.75, 0.73, 0.68)
    else:
        rgb = mix(wall, tuple(c * 0.85 for c in wall), fbm(rng, size, 4, 6))
    canvas = Canvas(size, 1.0, rgb)
    frame = random_colour(rng, (0.0, 0.4), (0.1, 0.95))
    x0, x1 = rng.uniform(0.18, 0.3), rng.uniform(0.7, 0.82)
    y0, y1 = rng.uniform(0.12, 0.25), rng.uniform(0.7, 0.8)
    canvas.rect((x0 - 0.03, y0 - 0.03, x1 + 0.03, y1 + 0.02), frame)
    sky_reflection = np.linspace(0.55, 0.2, size)[:, None, None] * np.array([0.8, 0.9, 1.0]) * np.ones((1, size, 1))
    glass_size = (int((x1 - x0) * canvas.w), int((y1 - y0) * canvas.h))
    glass = Image.fromarray(np.uint8(sky_reflection * 255)).resize(glass_size, Image.BILINEAR)
    canvas.image.paste(glass, (int(x0 * canvas.w), int(y0 * canvas.h)))
    canvas.draw_emission.rectangle([*canvas.px(x0, y0), *canvas.px(x1, y1)], fill=255)
    curtain = random_colour(rng, (0.2, 0.8), (0.5, 1.0))
    if rng.random() < 0.6:
        canvas.rect((x0, y0, x0 + (x1 - x0) * rng.uniform(0.15, 0.4), y1), curtain)
    canvas.rect(((x0 + x1) / 2 - 0.01, y0, (x0 + x1) / 2 + 0.01, y1), frame)
    canvas.rect((x0, (y0 + y1) / 2 - 0.01, x1, (y0 + y1) / 2 + 0.01), frame)
    canvas.rect((x0 - 0.06, y1 + 0.02, x1 + 0.06, y1 + 0.05), tuple(c * 0.7 for c in wall))
    return canvas.result()


def door(rng: np.random.Generator, glyphs: Glyphs, size: int, aspect: float) -> np.ndarray:
    """A street door: surround, panelled leaf with a glazed top, handle and a number plate."""
    surround = random_colour(rng, (0.0, 0.3), (0.3, 0.9))
    leaf = random_colour(rng, (0.3, 1.0), (0.15, 0.8))
    canvas = Canvas(size, aspect, surround)
    canvas.rect((0.12, 0.08, 0.88, 1.0), leaf)
    canvas.rect((0.2, 0.12, 0.8, 0.35), (0.25, 0.3, 0.35), emission=0.6)
    for top in (0.42, 0.7):
        canvas.rect(
            (0.2, top, 0.8, top + 0.22), tuple(c * 0.8 for c in leaf), outline=tuple(c * 0.5 for c in leaf), width=0.008
        )
    canvas.ellipse((0.72, 0.6, 0.8, 0.64), (0.85, 0.75, 0.3))
    canvas.rect((0.3, 0.015, 0.7, 0.065), (0.95, 0.95, 0.9))
    canvas.text(glyphs, glyphs.word(rng, 1, 3), (0.32, 0.02, 0.68, 0.06), (0.1, 0.1, 0.3))
    return grain(rng, canvas.result(), 0.12)


def graffiti(rng: np.random.Generator, glyphs: Glyphs, size: int, aspect: float) -> np.ndarray:
    """A tag on a wall patch: outlined thick strokes, bubble lettering and drips."""
    wall = random_colour(rng, (0.0, 0.3), (0.4, 0.8))
    canvas = Canvas(size, aspect, mix(wall, tuple(c * 0.7 for c in wall), fbm(rng, size, 4, 6)))
    for _ in range(rng.integers(2, 5)):
        colour = random_colour(rng, (0.7, 1.0), (0.6, 1.0))
        points = np.cumsum(rng.normal(0.0, 0.12, (rng.integers(4, 8), 2)), axis=0) + rng.uniform(0.2, 0.8, 2)
        points = [tuple(p) for p in np.clip(points, 0.02, 0.98)]
        canvas.line(points, (0.05, 0.05, 0.05), rng.uniform(0.08, 0.14))
        canvas.line(points, colour, rng.uniform(0.04, 0.07))
        for x, y in points[::2]:
            canvas.line([(x, y), (x, min(1.0, y + rng.uniform(0.05, 0.2)))], colour, 0.01)
    ink = random_colour(rng, (0.8, 1.0), (0.8, 1.0))
    canvas.text(glyphs, glyphs.word(rng, 3, 6), (0.05, 0.3, 0.95, 0.75), ink, weight=0.22)
    return grain(rng, canvas.result(), 0.1)


def asphalt_road(rng: np.random.Generator, size: int, dash_fraction: float) -> np.ndarray:
    """Asphalt with cracks, a dashed centre line (at v = 0.5) and solid edge lines (tileable)."""
    rgb = mix((0.22, 0.22, 0.23), (0.4, 0.39, 0.37), fbm(rng, size, 8, 7, 0.65))
    cracks = np.abs(fbm(rng, size, 6, 4) - 0.5) < 0.012
    rgb[cracks] *= 0.55
    y, x = np.mgrid[0:size, 0:size] / size
    paint = np.array([0.92, 0.9, 0.82])
    rgb[(np.abs(y - 0.5) < 0.008) & (x < dash_fraction)] = paint
    rgb[(np.abs(y - 0.035) < 0.008) | (np.abs(y - 0.965) < 0.008)] = paint
    return rgbe(rgb * (0.85 + 0.3 * fbm(rng, size, 32, 2))[..., None])


def clouds(rng: np.random.Generator, size: int) -> np.ndarray:
    """Cloud cover (tileable): alpha in the first channel, low frequency only."""
    cover = np.clip((fbm(rng, size, 3, 5, 0.55) - 0.45) * 3.0, 0.0, 1.0)
    return rgbe(np.repeat(cover[..., None], 3, axis=-1))


def fabric(rng: np.random.Generator, size: int) -> np.ndarray:
    """Clothing: a base colour with stripes, checks, dots or a print (tileable)."""
    base, second = random_colour(rng, (0.2, 1.0), (0.15, 0.95)), random_colour(rng, (0.2, 1.0), (0.15, 0.95))
    y, x = np.mgrid[0:size, 0:size] / size
    kind = rng.integers(0, 4)
    pattern = [
        (np.sin(2 * math.pi * 6 * y) > 0.3),
        (np.sin(2 * math.pi * 5 * x) > 0) ^ (np.sin(2 * math.pi * 5 * y) > 0),
        ((x * 8 % 1 - 0.5) ** 2 + (y * 8 % 1 - 0.5) ** 2) < 0.06,
        fbm(rng, size, 4, 4) > 0.55,
    ][kind].astype(float)
    return rgbe(mix(base, second, pattern) * (0.85 + 0.3 * fbm(rng, size, 16, 3))[..., None])


def skin(rng: np.random.Generator, size: int) -> np.ndarray:
    """A head: skin tone with hair on top and a darker band for the eyes (one copy per face)."""
    tone = colorsys.hsv_to_rgb(rng.uniform(0.04, 0.1), rng.uniform(0.3, 0.6), rng.uniform(0.35, 0.95))
    canvas = Canvas(size, 1.0, tone)
    canvas.rect((0.0, 0.0, 1.0, rng.uniform(0.15, 0.4)), random_colour(rng, (0.2, 0.7), (0.05, 0.5)))
    canvas.rect((0.2, 0.45, 0.8, 0.52), tuple(c * 0.5 for c in tone))
    return canvas.result()


def car_body(rng: np.random.Generator, size: int, aspect: float) -> np.ndarray:
    """A car side: paint with a door seam, wheel arches, lights and a plate (one copy per face)."""
    paint = random_colour(rng, (0.0, 0.9), (0.2, 0.95))
    canvas = Canvas(size, aspect, mix(paint, tuple(c * 0.8 for c in paint), fbm(rng, size, 2, 3)))
    for x in (0.2, 0.8):
        canvas.ellipse((x - 0.1, 0.55, x + 0.1, 0.55 + 0.2 * aspect), (0.05, 0.05, 0.05))
        canvas.ellipse((x - 0.05, 0.6, x + 0.05, 0.6 + 0.1 * aspect), (0.6, 0.6, 0.62))
    canvas.rect((0.48, 0.05, 0.49, 0.6), tuple(c * 0.5 for c in paint))
    canvas.rect((0.0, 0.15, 0.04, 0.35), (1.0, 0.9, 0.6), emission=1.0)
    canvas.rect((0.96, 0.15, 1.0, 0.35), (0.9, 0.1, 0.1), emission=0.8)
    canvas.rect((0.42, 0.4, 0.58, 0.5), (0.95, 0.95, 0.9))
    return canvas.result()


def tinted_glass(size: int) -> np.ndarray:
    """Dark car glass with a soft reflection gradient."""
    y = np.linspace(0.0, 1.0, size)[:, None] * np.ones((1, size))
    return rgbe(mix((0.35, 0.4, 0.45), (0.08, 0.09, 0.1), y))


def metal(rng: np.random.Generator, size: int, colour: Colour) -> np.ndarray:
    """Painted metal with scratches (tileable)."""
    rgb = mix(colour, tuple(c * 0.7 for c in colour), fbm(rng, size, 8, 6))
    return rgbe(rgb)
