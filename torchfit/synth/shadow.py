"""The body's cast shadow on every background surface: a shadow map for a directional light.

The body is rasterised orthographically as seen from the light (the z-buffer rasteriser of
:mod:`torchfit.synth.raster`, in a light frame ``(u, v, depth)`` with ``depth`` growing away
from the light); a surface point is in the body's shadow when the map holds a body surface
nearer to the light than the point (minus a small bias). Unlike the standard renderer's floor
shadow (the body projected on the plane z = 0), this darkens walls, boxes and furniture too.
World frame of design.md section 2, metres.
"""

from __future__ import annotations

import numpy as np

from torchfit.errors import ShapeError
from torchfit.synth.raster import rasterize

__all__ = ["light_frame", "shadow_map_test"]

_DEPTH_OFFSET = 100.0  # keeps light-frame depths positive for the rasteriser (metres)


def light_frame(direction: np.ndarray) -> np.ndarray:
    """(3, 3) rows ``u, v, -l``: two axes across a directional light and the direction the
    light travels (``direction`` is the unit vector towards the light)."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.95 else np.array([1.0, 0.0, 0.0])
    u = np.cross(up, d)
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    return np.stack([u, v, -d])


def shadow_map_test(
    vertices: np.ndarray,
    faces: np.ndarray,
    direction: np.ndarray,
    points: np.ndarray,
    texel_m: float = 0.003,
    bias_m: float = 0.015,
) -> np.ndarray:
    """Which points lie in the shadow that the body casts along a directional light.

    Args:
        vertices: (V, 3) body vertices, world frame, metres.
        faces: (F, 3) vertex indices.
        direction: (3,) unit vector towards the light.
        points: (..., 3) surface points, world frame (NaN where there is none).
        texel_m: the shadow map's texel size, metres.
        bias_m: a point is shadowed only if the body is nearer the light by more than this.

    Returns:
        (...) bool, True where the body hides the light from the point.

    Raises:
        ShapeError: a wrong shape of ``vertices`` or ``points``.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ShapeError(f"vertices: expected shape (V, 3), got {vertices.shape}")
    if points.shape[-1:] != (3,):
        raise ShapeError(f"points: expected shape (..., 3), got {points.shape}")
    frame = light_frame(direction)
    body = vertices @ frame.T
    lo = body[:, :2].min(0) - 4 * texel_m
    hi = body[:, :2].max(0) + 4 * texel_m
    size = np.ceil((hi - lo) / texel_m).astype(int) + 1
    offset = _DEPTH_OFFSET - body[:, 2].min()
    raster = rasterize((body[:, :2] - lo) / texel_m, body[:, 2] + offset, faces, tuple(size))
    flat = points.reshape(-1, 3)
    out = np.zeros(flat.shape[0], dtype=bool)
    ok = np.isfinite(flat).all(1)
    q = flat[ok] @ frame.T
    ij = np.round((q[:, :2] - lo) / texel_m).astype(np.int64)
    inside = (ij >= 0).all(1) & (ij[:, 0] < size[0]) & (ij[:, 1] < size[1])
    depth = np.full(q.shape[0], np.inf)
    depth[inside] = raster.depth[ij[inside, 1], ij[inside, 0]]
    out[np.nonzero(ok)[0]] = depth < q[:, 2] + offset - bias_m
    return out.reshape(points.shape[:-1])
