"""The room, the light, the cameras and the image formation of synthetic captures.

World frame of design.md section 2: z up, floor z = 0, the person stands on the origin. A
room is described in the frame of its main camera's azimuth: ``f`` (horizontal, from the origin
towards the camera), ``s = z x f`` and ``z``. Background surfaces are ray-cast per pixel (exact
perspective and lens distortion, via ``cv2.undistortPoints``); the body is z-buffered on top
(:mod:`torchfit.synth.raster`). Light is one directional source plus ambient; the body's
shadow on the floor is the body projected along the light and rasterised in the image.
Colours are linear RGB in [0, 1]; images are written as 8-bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from torchfit.camera import Camera, look_at, project_points
from torchfit.synth.raster import interpolate, lambert, rasterize, vertex_normals

__all__ = [
    "Box",
    "Room",
    "Light",
    "sample_room",
    "sample_camera",
    "render",
    "room_depth",
    "body_coverage",
    "finish",
]


@dataclass
class Box:
    """An axis-aligned box in the room frame: ``lo``/``hi`` are (f, s, z) corners, metres."""

    lo: np.ndarray
    hi: np.ndarray
    colour: np.ndarray


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


# --------------------------------------------------------------------------------------------
# Background ray casting


def _pixel_rays(camera: Camera) -> np.ndarray:
    """(H, W, 3) world directions (not normalised) of the pixel rays, through the distortion."""
    width, height = camera.image_size
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pts = np.stack([u, v], -1).reshape(-1, 1, 2)
    K = camera.K[0].numpy()
    dist = camera.dist[0].numpy()
    xy = cv2.undistortPoints(
        pts, K, dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-10)
    ).reshape(-1, 2)
    rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], 1) @ camera.R[0].numpy()  # R^T d
    return rays.reshape(height, width, 3)


def _value_noise(grid: np.ndarray, a: np.ndarray, b: np.ndarray, scale: float) -> np.ndarray:
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


def _hash(*ints: np.ndarray) -> np.ndarray:
    """A deterministic pseudo-random value in [0, 1) per integer tuple."""
    h = np.zeros_like(ints[0], dtype=np.float64)
    for k, i in enumerate(ints):
        h = h + i * (12.9898 + 17.17 * k)
    return (np.sin(h) * 43758.5453) % 1.0


def _floor_albedo(room: Room, p: np.ndarray) -> np.ndarray:
    fa, sa = p[..., 0], p[..., 1]
    if room.floor_kind == "planks":
        row = np.floor(sa / room.plank_width)
        col = np.floor((fa + _hash(row) * 3.0) / 1.2)
        tone = _hash(row, col)
        grain = 0.025 * np.sin(fa * 45 + 8 * _hash(row) + 1.5 * np.sin(fa * 7 + sa * 13))
        seam = (np.abs(sa / room.plank_width - np.round(sa / room.plank_width)) < 0.03) | (
            np.abs((fa + _hash(row) * 3.0) / 1.2 - np.round((fa + _hash(row) * 3.0) / 1.2)) < 0.004
        )
    else:
        size = room.plank_width * 3
        row, col = np.floor(sa / size), np.floor(fa / size)
        tone = (row + col) % 2 * 0.7 + 0.3 * _hash(row, col)
        grain = 0.0
        seam = (np.abs(sa / size - np.round(sa / size)) < 0.02) | (
            np.abs(fa / size - np.round(fa / size)) < 0.02
        )
    a, b = room.floor_colours
    col_rgb = a * (1 - tone[..., None]) + b * tone[..., None]
    col_rgb = col_rgb * (1 + grain + 0.05 * _value_noise(room.noise, fa, sa, 0.4))[..., None]
    return np.where(seam[..., None], col_rgb * 0.6, col_rgb)


def _wall_albedo(room: Room, a: np.ndarray, z: np.ndarray, back: bool) -> np.ndarray:
    base = room.wall_colour * (1 + 0.03 * _value_noise(room.noise, a, z, 0.5))[..., None]
    skirting = (z < 0.09)[..., None]
    out = np.where(skirting, np.array([0.92, 0.92, 0.9]), base)
    if back:
        for (s0, z0), (s1, z1), colour in room.pictures:
            inside = (a >= s0) & (a <= s1) & (z >= z0) & (z <= z1)
            frame = inside & ~(
                (a >= s0 + 0.03) & (a <= s1 - 0.03) & (z >= z0 + 0.03) & (z <= z1 - 0.03)
            )
            stripes = colour * (0.75 + 0.25 * np.sin(a * 23 + z * 11))[..., None]
            out = np.where(inside[..., None], stripes, out)
            out = np.where(frame[..., None], np.array([0.2, 0.15, 0.1]), out)
    return out


def _background(
    room: Room, camera: Camera, light: Light
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast the room: (H, W, 3) shaded colour, (H, W) depth, (H, W) floor mask + points."""
    basis = room.basis
    centre = camera.centre[0].numpy() @ basis.T  # in (f, s, z)
    rays = _pixel_rays(camera) @ basis.T
    h, w, _ = rays.shape
    best = np.full((h, w), np.inf)
    normal = np.zeros((h, w, 3))
    albedo = np.zeros((h, w, 3))
    kind = np.zeros((h, w), dtype=np.int8)  # 1 floor

    def plane(axis: int, value: float, n: np.ndarray, code: int) -> None:
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (value - centre[axis]) / rays[..., axis]
        hit = (t > 1e-6) & (t < best)
        best[hit] = t[hit]
        normal[hit] = n
        kind[hit] = code

    plane(2, 0.0, np.array([0, 0, 1.0]), 1)
    plane(2, room.ceiling, np.array([0, 0, -1.0]), 2)
    plane(0, -room.back, np.array([1.0, 0, 0]), 3)
    plane(0, room.front, np.array([-1.0, 0, 0]), 4)
    plane(1, room.half_width, np.array([0, -1.0, 0]), 5)
    plane(1, -room.half_width, np.array([0, 1.0, 0]), 6)
    p = centre + best[..., None] * rays
    albedo[kind == 1] = _floor_albedo(room, p[kind == 1])
    albedo[kind == 2] = np.array([0.9, 0.9, 0.9])
    for code, back in ((3, True), (4, False)):
        m = kind == code
        albedo[m] = _wall_albedo(room, p[m][:, 1], p[m][:, 2], back)
    for code in (5, 6):
        m = kind == code
        albedo[m] = _wall_albedo(room, p[m][:, 0], p[m][:, 2], False)
    # boxes (slab test)
    for box in room.boxes:
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (box.lo - centre) / rays
            t1 = (box.hi - centre) / rays
        tmin = np.minimum(t0, t1)
        tnear = tmin.max(-1)
        tfar = np.maximum(t0, t1).min(-1)
        hit = (tnear <= tfar) & (tnear > 1e-6) & (tnear < best)
        axis = np.argmax(tmin, -1)
        n = np.zeros((h, w, 3))
        np.put_along_axis(
            n, axis[..., None], -np.sign(np.take_along_axis(rays, axis[..., None], -1)), -1
        )
        best[hit] = tnear[hit]
        normal[hit] = n[hit]
        kind[hit] = 7
        q = centre + tnear[..., None] * rays
        tex = 1 + 0.04 * np.sin(q[..., 0] * 40 + q[..., 1] * 40 + q[..., 2] * 90)
        albedo[hit] = (box.colour * tex[..., None])[hit]
        p[hit] = q[hit]
    world_normal = normal @ basis
    colour = lambert(albedo, world_normal, light.direction, light.ambient, light.diffuse)
    # depth along the optical axis
    cam_z = (p @ basis) @ camera.R[0].numpy()[2] + camera.t[0, 2].item()
    floor_points = p @ basis
    return colour, cam_z, np.where((kind == 1)[..., None], floor_points, np.nan)


# --------------------------------------------------------------------------------------------
# Rendering


def _project(points: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    px, depth = project_points(torch.from_numpy(points)[None], camera, return_depth=True)
    return px[0].numpy(), depth[0].numpy()


def body_coverage(
    camera: Camera, vertices: np.ndarray, faces: np.ndarray, room_depth: np.ndarray
) -> np.ndarray:
    """Where the body is visible in front of the room: the true person silhouette.

    Args:
        camera: the view.
        vertices: (V, 3) world, metres.
        faces: (F, 3) vertex indices.
        room_depth: (H, W) camera-frame depth of the room surfaces, metres.

    Returns:
        (H, W) bool, True where a body triangle covers the pixel centre nearer than the room.
    """
    px, dep = _project(vertices, camera)
    raster = rasterize(px, dep, faces, camera.image_size)
    return raster.mask & (raster.depth < room_depth)


def room_depth(room: Room, camera: Camera, light: Light) -> np.ndarray:
    """(H, W) camera-frame depth of the empty room, metres (for :func:`body_coverage`)."""
    return _background(room, camera, light)[1]


def render(
    room: Room,
    camera: Camera,
    light: Light,
    body: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    shadow_strength: float = 1.0,
    layers: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one view: the room and, optionally, a body with its floor shadow.

    Args:
        room, camera, light: the scene.
        body: ``(vertices (V, 3) world, faces (F, 3), albedo (V, 3))`` or None for an empty
            room.
        shadow_strength: 1 for a full cast shadow (ambient light only inside it).
        layers: also return the true person and cast-shadow masks (evaluation data).

    Returns:
        (H, W, 3) float RGB in [0, 1] before noise; with ``layers``, the tuple
        ``(colour, person, shadow)``: ``person`` (H, W) bool where the body is visible (the
        same coverage that is painted), ``shadow`` (H, W) bool where the blurred cast shadow
        darkens the floor by at least half its full strength and no body is visible.
    """
    colour, depth, floor_points = _background(room, camera, light)
    h, w = depth.shape
    if body is None:
        if layers:
            return colour, np.zeros((h, w), bool), np.zeros((h, w), bool)
        return colour
    vertices, faces, albedo = body
    size = camera.image_size
    # cast shadow: the body projected on the floor along the light
    L = light.direction
    shadow_pts = vertices - (vertices[:, 2:3] / L[2]) * L[None]
    spx, sdepth = _project(shadow_pts, camera)
    shadow = rasterize(spx, sdepth, faces, size).mask.astype(np.float32)
    shadow = cv2.GaussianBlur(shadow, (0, 0), 1.5)
    is_floor = np.isfinite(floor_points[..., 0])
    lit = light.ambient + light.diffuse * max(L[2], 0.0)
    ratio = light.ambient / lit
    factor = 1 - shadow_strength * shadow * is_floor * (1 - ratio)
    colour = colour * factor[..., None]
    # the body, z-buffered against the room
    px, dep = _project(vertices, camera)
    raster = rasterize(px, dep, faces, size)
    visible = raster.mask & (raster.depth < depth)
    normals = interpolate(raster, faces, vertex_normals(vertices, faces))
    alb = interpolate(raster, faces, albedo)
    shaded = lambert(alb, normals, L, light.ambient, light.diffuse)
    colour[visible] = shaded[visible]
    if layers:
        cast = (shadow * is_floor >= 0.5) & ~visible & (shadow_strength > 0)
        return colour, visible, cast
    return colour


def finish(
    colour: np.ndarray,
    rng: np.random.Generator,
    gain: np.ndarray,
    noise_sigma: float,
    blur_sigma: float = 0.6,
) -> np.ndarray:
    """Optics blur, illumination gain (per channel), sensor noise, gamma and 8-bit quantisation.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    img = (
        cv2.GaussianBlur(colour.astype(np.float32), (0, 0), blur_sigma)
        if blur_sigma > 0
        else colour
    )
    img = np.clip(img * gain[None, None, :], 0, 1) ** (1 / 2.2) * 255.0
    img = img + rng.normal(0.0, noise_sigma, img.shape) * np.sqrt(0.3 + img / 255.0)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)
