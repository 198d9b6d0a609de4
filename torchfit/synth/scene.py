"""The room, the light, the cameras and the image formation of synthetic captures.

World frame of design.md section 2: z up, floor z = 0, the person stands on the origin. A
room is described in the frame of its main camera's azimuth: ``f`` (horizontal, from the origin
towards the camera), ``s = z x f`` and ``z``. Background surfaces are ray-cast per pixel (exact
perspective and lens distortion, via ``cv2.undistortPoints``); the body is z-buffered on top
(:mod:`torchfit.synth.raster`). Light is one directional source plus ambient; the body's
shadow on the floor is the body projected along the light and rasterised in the image, or,
for the hard rooms, a shadow map that darkens every surface (:mod:`torchfit.synth.shadow`).
The room itself is drawn in :mod:`torchfit.synth.room`, its textures in
:mod:`torchfit.synth.texture`. Colours are linear RGB in [0, 1]; images are written as 8-bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from torchfit.camera import Camera, project_points
from torchfit.synth.raster import interpolate, lambert, rasterize, vertex_normals
from torchfit.synth.room import Box, Light, Room, sample_camera, sample_room
from torchfit.synth.shadow import shadow_map_test
from torchfit.synth.texture import furniture_albedo, pattern_albedo, poster_albedo
from torchfit.synth.texture import hash01 as _hash
from torchfit.synth.texture import value_noise as _value_noise

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
    if room.pattern is not None:
        base = pattern_albedo(room.pattern, a, z) * (base / room.wall_colour)
    skirting = (z < (0.09 if room.skirting else -1.0))[..., None]
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
        for poster in room.posters:
            (s0, z0), (s1, z1) = poster.lo, poster.hi
            inside = (a >= s0) & (a <= s1) & (z >= z0) & (z <= z1)
            out[inside] = poster_albedo(poster, a[inside], z[inside])
    return out


@dataclass
class _Surfaces:
    """The ray-cast empty room, per pixel: shaded ``colour`` (H, W, 3), camera-frame
    ``depth`` (H, W), world ``points`` (H, W, 3) and unit ``normals`` (H, W, 3), and ``kind``
    (H, W) int8: 1 floor, 2 ceiling, 3-6 walls, 7 boxes."""

    colour: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    kind: np.ndarray


def _background(room: Room, camera: Camera, light: Light) -> _Surfaces:
    """Ray-cast the room (walls, floor, ceiling, boxes) and shade it."""
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
        if box.texture != "plain":  # furniture: its front (facing +f) carries the texture
            front = hit & (axis == 0)
            albedo[front] = furniture_albedo(
                box.texture, box.colour, q[front][:, 1], q[front][:, 2], box.lo, box.hi
            )
        p[hit] = q[hit]
    world_normal = normal @ basis
    colour = lambert(albedo, world_normal, light.direction, light.ambient, light.diffuse)
    # depth along the optical axis
    cam_z = (p @ basis) @ camera.R[0].numpy()[2] + camera.t[0, 2].item()
    return _Surfaces(colour, cam_z, p @ basis, world_normal, kind)


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
    return _background(room, camera, light).depth


def render(
    room: Room,
    camera: Camera,
    light: Light,
    body: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    shadow_strength: float = 1.0,
    layers: bool = False,
    all_surfaces: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one view: the room and, optionally, a body with its cast shadow.

    Args:
        room, camera, light: the scene.
        body: ``(vertices (V, 3) world, faces (F, 3), albedo (V, 3))`` or None for an empty
            room.
        shadow_strength: 1 for a full cast shadow (ambient light only inside it).
        layers: also return the true person and cast-shadow masks (evaluation data).
        all_surfaces: cast the body's shadow on every surface the light reaches (walls,
            boxes, furniture, floor) with a shadow map (:mod:`torchfit.synth.shadow`); by
            default it falls on the floor only (the body projected on z = 0).

    Returns:
        (H, W, 3) float RGB in [0, 1] before noise; with ``layers``, the tuple
        ``(colour, person, shadow)``: ``person`` (H, W) bool where the body is visible (the
        same coverage that is painted), ``shadow`` (H, W) bool where the blurred cast shadow
        reaches at least half its full strength on a surface it darkens (the floor; with
        ``all_surfaces`` any surface facing the light whose full shadow would remove at least
        10 % of its light) and no body is visible.
    """
    surf = _background(room, camera, light)
    colour, depth = surf.colour, surf.depth
    h, w = depth.shape
    if body is None:
        if layers:
            return colour, np.zeros((h, w), bool), np.zeros((h, w), bool)
        return colour
    vertices, faces, albedo = body
    size = camera.image_size
    L = light.direction
    if all_surfaces:  # shadow map: the body as seen from the light, tested per surface point
        hidden = shadow_map_test(vertices, faces, L, surf.points).astype(np.float32)
        shadow = cv2.GaussianBlur(hidden, (0, 0), 1.5)
        lit = light.ambient + light.diffuse * np.clip(surf.normals @ L, 0.0, None)
        receives = 1 - light.ambient / lit >= 0.1
        factor = 1 - shadow_strength * shadow * (1 - light.ambient / lit)
    else:  # the body projected on the floor along the light
        shadow_pts = vertices - (vertices[:, 2:3] / L[2]) * L[None]
        spx, sdepth = _project(shadow_pts, camera)
        shadow = rasterize(spx, sdepth, faces, size).mask.astype(np.float32)
        shadow = cv2.GaussianBlur(shadow, (0, 0), 1.5)
        receives = surf.kind == 1
        lit = light.ambient + light.diffuse * max(L[2], 0.0)
        ratio = light.ambient / lit
        factor = 1 - shadow_strength * shadow * receives * (1 - ratio)
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
        cast = (shadow * receives >= 0.5) & ~visible & (shadow_strength > 0)
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
