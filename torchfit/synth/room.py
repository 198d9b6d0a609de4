"""The room, its furniture, the light and the cameras of a synthetic capture (random draws).

A room is described in the frame of its main camera's azimuth: ``f`` (horizontal, from the
origin towards the camera), ``s = z x f`` and ``z`` (design.md section 2: z up, floor z = 0,
the person stands on the origin). Colours are linear RGB in [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from torchfit.camera import Camera, look_at
from torchfit.synth.texture import Poster, WallPattern

__all__ = ["Box", "Room", "Light", "sample_room", "sample_camera"]


@dataclass
class Box:
    """An axis-aligned box in the room frame: ``lo``/``hi`` are (f, s, z) corners, metres."""

    lo: np.ndarray
    hi: np.ndarray
    colour: np.ndarray
    texture: str = "plain"  # or a front of texture.FURNITURE: "books", "door", "cabinet"


@dataclass
class Room:
    """A rectangular room around the origin, in the frame (f, s, z) of ``azimuth``."""

    azimuth: float  # radians, the direction of f in the world xy plane
    back: float  # back wall at f = -back
    front: float  # wall behind the camera at f = +front
    half_width: float  # side walls at s = +-half_width
    ceiling: float
    wall_colour: np.ndarray
    floor_colours: np.ndarray  # (2, 3) two tones
    floor_kind: str  # "planks" or "tiles"
    plank_width: float
    noise: np.ndarray  # (G, G) low-frequency value noise in [-1, 1]
    boxes: list[Box] = field(default_factory=list)
    pictures: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    # pictures: ((s0, z0), (s1, z1), colour) rectangles on the back wall
    pattern: WallPattern | None = None  # hard rooms: the walls' pattern (None: plain paint)
    posters: list[Poster] = field(default_factory=list)  # hard rooms: posters, back wall
    skirting: bool = True  # a light skirting board along the walls (none on a green screen)

    @property
    def basis(self) -> np.ndarray:
        """(3, 3) rows f, s, z in world coordinates."""
        c, s = math.cos(self.azimuth), math.sin(self.azimuth)
        return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Light:
    """A directional light (unit vector towards the light) and ambient intensity."""

    direction: np.ndarray
    ambient: float
    diffuse: float


def sample_room(rng: np.random.Generator, azimuth: float, camera_distance: float) -> Room:
    """A random room whose main camera stands at ``azimuth``, ``camera_distance`` away."""
    wall = rng.choice(
        np.array(
            [
                [0.85, 0.83, 0.78],
                [0.78, 0.82, 0.80],
                [0.86, 0.80, 0.70],
                [0.70, 0.74, 0.80],
                [0.80, 0.78, 0.74],
                [0.62, 0.66, 0.60],
            ]
        )
    ) * rng.uniform(0.9, 1.05)
    kind = str(rng.choice(["planks", "tiles"]))
    if kind == "planks":
        base = rng.choice(np.array([[0.55, 0.38, 0.22], [0.62, 0.48, 0.32], [0.40, 0.28, 0.18]]))
    else:
        base = rng.choice(np.array([[0.55, 0.55, 0.52], [0.45, 0.42, 0.40], [0.62, 0.58, 0.50]]))
    floor = np.stack([base, base * rng.uniform(0.8, 0.92)])
    back = rng.uniform(1.5, 2.3)
    half = rng.uniform(2.6, 3.6)
    boxes = []
    # clutter along the back wall, away from the middle, and along the side walls
    for sign in (-1, 1):
        if rng.random() < 0.8:
            width, depth, height = (
                rng.uniform(0.5, 1.2),
                rng.uniform(0.35, 0.6),
                rng.uniform(0.5, 1.9),
            )
            s0 = sign * rng.uniform(0.9, half - width - 0.1)
            s_lo, s_hi = sorted((s0, s0 + sign * width))
            boxes.append(
                Box(
                    np.array([-back, s_lo, 0.0]),
                    np.array([-back + depth, s_hi, height]),
                    rng.uniform(0.15, 0.75, 3),
                )
            )
        if rng.random() < 0.6:
            f0 = rng.uniform(-back + 0.2, 1.0)
            size = rng.uniform(0.3, 0.6, 3) * np.array([1.0, 1.0, 1.5])
            s_edge = sign * half
            s_lo, s_hi = sorted((s_edge, s_edge - sign * size[1]))
            boxes.append(
                Box(
                    np.array([f0, s_lo, 0.0]),
                    np.array([f0 + size[0], s_hi, size[2]]),
                    rng.uniform(0.15, 0.75, 3),
                )
            )
    pictures = []
    for _ in range(rng.integers(1, 4)):
        s0, z0 = rng.uniform(-2.0, 1.6), rng.uniform(1.2, 1.8)
        w, h = rng.uniform(0.3, 0.8), rng.uniform(0.25, 0.6)
        pictures.append((np.array([s0, z0]), np.array([s0 + w, z0 + h]), rng.uniform(0.1, 0.9, 3)))
    return Room(
        azimuth=azimuth,
        back=back,
        front=camera_distance + rng.uniform(0.8, 1.5),
        half_width=half,
        ceiling=rng.uniform(2.6, 3.0),
        wall_colour=wall,
        floor_colours=floor,
        floor_kind=kind,
        plank_width=rng.uniform(0.1, 0.2),
        noise=rng.uniform(-1, 1, (9, 9)),
        boxes=boxes,
        pictures=pictures,
    )


def sample_camera(
    rng: np.random.Generator,
    centre: np.ndarray,
    target: np.ndarray,
    image_size: tuple[int, int],
    view_height_m: float,
) -> Camera:
    """A camera at ``centre`` looking at ``target``, its focal length such that about
    ``view_height_m`` metres are seen vertically at the target, with a little lens distortion.
    """
    width, height = image_size
    d = float(np.linalg.norm(target - centre))
    f = height * d / view_height_m
    K = torch.tensor(
        [
            [f, 0.0, (width - 1) / 2 + rng.uniform(-6, 6)],
            [0.0, f * rng.uniform(0.998, 1.002), (height - 1) / 2 + rng.uniform(-6, 6)],
            [0.0, 0.0, 1.0],
        ],
        dtype=torch.float64,
    )
    dist = torch.tensor(
        [
            rng.uniform(-0.08, 0.02),
            rng.uniform(-0.02, 0.05),
            rng.uniform(-5e-4, 5e-4),
            rng.uniform(-5e-4, 5e-4),
            0.0,
        ],
        dtype=torch.float64,
    )
    R, t = look_at(torch.from_numpy(centre)[None], torch.from_numpy(target)[None])
    return Camera(K=K, dist=dist, R=R[0], t=t[0], image_size=image_size)
