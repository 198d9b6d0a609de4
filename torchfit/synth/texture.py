"""Procedural surface textures of the synthetic rooms (albedo as a function of position).

Every function takes surface coordinates in metres and returns linear RGB albedo in [0, 1]:
walls use ``(a, z)`` (``a`` the horizontal coordinate along the wall, ``z`` the height),
box faces the hit points in the room frame ``(f, s, z)`` of :mod:`torchfit.synth.room`.
The hard rooms' patterns (stripes, checks, wallpaper), posters and furniture fronts (book
spines, door, cabinet) are strong, high-contrast textures on purpose: a background model must
not take them for the person when the light or the exposure changes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "WallPattern",
    "Poster",
    "value_noise",
    "hash01",
    "pattern_albedo",
    "poster_albedo",
    "furniture_albedo",
    "sample_pattern",
    "sample_poster",
]

WALL_PATTERNS = ("stripes", "checks", "wallpaper")
FURNITURE = ("books", "door", "cabinet")


@dataclass
class WallPattern:
    """A repeating wall pattern: ``kind`` in :data:`WALL_PATTERNS`, two colours (2, 3) and a
    period in metres."""

    kind: str
    colours: np.ndarray
    period: float


@dataclass
class Poster:
    """A poster on the back wall: corners ``(s0, z0)``, ``(s1, z1)`` metres, a palette (4, 3)
    and a layout seed (blocks of colour and lines of dark 'text')."""

    lo: np.ndarray
    hi: np.ndarray
    palette: np.ndarray
    seed: float


def value_noise(grid: np.ndarray, a: np.ndarray, b: np.ndarray, scale: float) -> np.ndarray:
    """Bilinear value noise of period ``grid.shape * scale`` metres at coordinates (a, b)."""
    n = grid.shape[0]
    x = (a / scale) % (n - 1)
    y = (b / scale) % (n - 1)
    i, j = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - i, y - j
    return (
        grid[i, j] * (1 - fx) * (1 - fy)
        + grid[i + 1, j] * fx * (1 - fy)
        + grid[i, j + 1] * (1 - fx) * fy
        + grid[i + 1, j + 1] * fx * fy
    )


def hash01(*ints: np.ndarray) -> np.ndarray:
    """A deterministic pseudo-random value in [0, 1) per integer tuple."""
    h = np.zeros_like(ints[0], dtype=np.float64)
    for k, i in enumerate(ints):
        h = h + i * (12.9898 + 17.17 * k)
    return (np.sin(h) * 43758.5453) % 1.0


def _mix(colours: np.ndarray, t: np.ndarray) -> np.ndarray:
    return colours[0] * (1 - t[..., None]) + colours[1] * t[..., None]


def pattern_albedo(pattern: WallPattern, a: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(N, 3) albedo of a patterned wall at (a, z), metres."""
    p = pattern.period
    if pattern.kind == "stripes":  # vertical stripes of two widths, a thin dark pinstripe
        x = a / p
        t = ((x % 1.0) < 0.55).astype(float)
        out = _mix(pattern.colours, t)
        pin = np.abs((x + 0.275) % 1.0 - 0.5) < 0.04
        return np.where(pin[..., None], out * 0.45, out)
    if pattern.kind == "checks":  # checks with a lighter grout line
        i, j = np.floor(a / p), np.floor(z / p)
        out = _mix(pattern.colours, ((i + j) % 2).astype(float))
        grout = (np.abs(a / p - np.round(a / p)) < 0.03) | (np.abs(z / p - np.round(z / p)) < 0.03)
        return np.where(grout[..., None], np.array([0.9, 0.9, 0.88]), out)
    # wallpaper: staggered diamonds with a dot in each, on the base colour
    row = np.floor(z / p)
    x = a / p + 0.5 * (row % 2)
    u, v = x % 1.0 - 0.5, z / p % 1.0 - 0.5
    diamond = np.abs(u) + np.abs(v) < 0.42
    dot = u**2 + v**2 < 0.012
    out = np.where(diamond[..., None], pattern.colours[1], pattern.colours[0])
    return np.where(dot[..., None], pattern.colours[0] * 0.35, out)


def poster_albedo(poster: Poster, a: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(N, 3) albedo inside a poster (the caller masks its rectangle): a white margin, blocks
    of the palette's colours and rows of dark 'text'."""
    (s0, z0), (s1, z1) = poster.lo, poster.hi
    u = (a - s0) / max(s1 - s0, 1e-6)
    v = (z - z0) / max(z1 - z0, 1e-6)
    k = poster.seed
    bi, bj = np.floor(u * 3 + k % 1.0), np.floor(v * 4)
    pick = (hash01(bi + 31 * k, bj) * len(poster.palette)).astype(int)
    out = poster.palette[pick]
    line, word = np.floor(v * 60), np.floor(u * 25)
    text = (v < 0.3) & (line % 2 == 0) & (hash01(word, line) > 0.3)
    out = np.where(text[..., None], np.array([0.05, 0.05, 0.06]), out)
    margin = (u < 0.04) | (u > 0.96) | (v < 0.04) | (v > 0.96)
    return np.where(margin[..., None], np.array([0.93, 0.93, 0.9]), out)


def _books(colour: np.ndarray, s: np.ndarray, z: np.ndarray, top: float) -> np.ndarray:
    """Rows of book spines between shelf boards (front face coordinates s, z)."""
    shelf = 0.33
    row = np.floor(z / shelf)
    zz = z - row * shelf
    width = 0.025 + 0.03 * hash01(row, np.floor(s / 0.6))
    book = np.floor((s + 0.37 * row) / width)
    h = hash01(book, row)
    spine = np.stack([hash01(book, row, 1.0 + c) for c in range(3)], -1) * 0.85 + 0.05
    spine = np.where((h < 0.25)[..., None], spine * 0.4, spine)  # some dark bindings
    height = shelf * (0.6 + 0.32 * hash01(book + 7, row))
    out = np.where((zz < height)[..., None], spine, colour * 0.25)  # dark back above the books
    board = (zz < 0.022) | (z > top - 0.03)
    return np.where(board[..., None], colour, out)


def furniture_albedo(
    kind: str, colour: np.ndarray, s: np.ndarray, z: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """(N, 3) albedo of a furniture front (the face towards the camera) at (s, z), metres.

    Args:
        kind: one of :data:`FURNITURE`.
        colour: (3,) the wood or paint colour.
        s, z: (N,) coordinates on the front face.
        lo, hi: (3,) the box corners in the room frame (f, s, z).
    """
    if kind == "books":
        return _books(colour, s - lo[1], z, hi[2])
    u, v = s - lo[1], z - lo[2]
    width = hi[1] - lo[1]
    if kind == "door":  # frame, two panels, a handle
        frame = (u < 0.07) | (u > width - 0.07) | (v > hi[2] - lo[2] - 0.07)
        panel = (np.abs(u - width / 2) < width / 2 - 0.16) & (
            (np.abs(v - 1.45) < 0.45) | (np.abs(v - 0.5) < 0.35)
        )
        handle = (np.abs(u - (width - 0.14)) < 0.05) & (np.abs(v - 1.0) < 0.02)
        out = np.where(frame[..., None], colour * 0.55, colour)
        out = np.where(panel[..., None], colour * 0.8, out)
        return np.where(handle[..., None], np.array([0.75, 0.72, 0.6]), out)
    # cabinet: drawers 25 cm high with a dark gap and a knob each
    gap = (v % 0.25 < 0.012) | (np.abs(u - width / 2) < 0.006)
    knob = (np.abs(v % 0.25 - 0.17) < 0.018) & (np.abs((u % (width / 2)) - width / 4) < 0.04)
    out = np.where(gap[..., None], colour * 0.2, colour)
    return np.where(knob[..., None], np.array([0.85, 0.8, 0.55]), out)


def sample_pattern(rng: np.random.Generator) -> WallPattern:
    """A random strongly contrasted wall pattern."""
    kind = str(rng.choice(WALL_PATTERNS))
    base = rng.uniform(0.45, 0.9, 3)
    other = np.clip(base * rng.uniform(0.25, 0.6) + rng.uniform(-0.1, 0.1, 3), 0.03, 1.0)
    period = {"stripes": (0.06, 0.18), "checks": (0.1, 0.25), "wallpaper": (0.12, 0.22)}[kind]
    return WallPattern(kind, np.stack([base, other]), float(rng.uniform(*period)))


def sample_poster(rng: np.random.Generator, s_range: tuple[float, float]) -> Poster:
    """A random poster on the back wall with its left edge in ``s_range``, 0.9-2.0 m high."""
    s0 = rng.uniform(*s_range)
    w, h = rng.uniform(0.4, 0.8), rng.uniform(0.5, 0.9)
    z0 = rng.uniform(0.9, 2.0 - h * 0.5)
    palette = rng.uniform(0.05, 0.95, (4, 3))
    return Poster(np.array([s0, z0]), np.array([s0 + w, z0 + h]), palette, float(rng.random()))
