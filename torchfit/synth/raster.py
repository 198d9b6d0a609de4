"""A vectorised z-buffer triangle rasteriser and Lambert shading (numpy).

Conventions: pixel ``(0, 0)`` is the centre of the top-left pixel (design.md section 2); a
pixel belongs to a triangle when its centre lies inside it (edges included). Depth is the
camera-frame z in metres; barycentric weights are perspective-correct. Every candidate
(pixel, triangle) pair inside the triangles' bounding boxes is tested at once, in chunks, and
the nearest triangle wins per pixel: occlusion is exact wherever surfaces cross (painter's
ordering is not used).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchfit.errors import ShapeError

__all__ = ["Raster", "rasterize", "vertex_normals", "interpolate", "lambert"]


@dataclass
class Raster:
    """The result of :func:`rasterize` for an image of ``H`` x ``W`` pixels.

    Attributes:
        face: (H, W) int64 index of the visible triangle, -1 where none.
        depth: (H, W) float64 camera-frame depth of the visible surface, ``inf`` where none.
        bary: (H, W, 3) float64 perspective-correct barycentric weights (zero where none).
    """

    face: np.ndarray
    depth: np.ndarray
    bary: np.ndarray

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool, True where a triangle is visible."""
        return self.face >= 0


def rasterize(
    pixels: np.ndarray,
    depth: np.ndarray,
    faces: np.ndarray,
    image_size: tuple[int, int],
    near: float = 1e-3,
    chunk: int = 2_000_000,
) -> Raster:
    """Rasterise triangles with a z-buffer.

    Args:
        pixels: (V, 2) projected vertices ``(u, v)`` in pixels.
        depth: (V,) camera-frame depth of the vertices, metres.
        faces: (F, 3) vertex indices.
        image_size: ``(width, height)``.
        near: triangles with a vertex nearer than this are skipped.
        chunk: largest number of (pixel, triangle) candidates tested at once (memory bound).

    Returns:
        A :class:`Raster`.

    Raises:
        ShapeError: inconsistent array shapes.
    """
    pixels = np.asarray(pixels, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if pixels.ndim != 2 or pixels.shape[1] != 2:
        raise ShapeError(f"pixels: expected shape (V, 2), got {pixels.shape}")
    if depth.shape != pixels.shape[:1]:
        raise ShapeError(f"depth: expected shape ({pixels.shape[0]},), got {depth.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ShapeError(f"faces: expected shape (F, 3), got {faces.shape}")
    width, height = image_size
    zbuf = np.full(height * width, np.inf)
    fbuf = np.full(height * width, -1, dtype=np.int64)
    bbuf = np.zeros((height * width, 3))

    tri = pixels[faces]  # (F, 3, 2)
    z = depth[faces]  # (F, 3)
    xmin = np.ceil(tri[..., 0].min(1)).clip(0, width - 1)
    xmax = np.floor(tri[..., 0].max(1)).clip(-1, width - 1)
    ymin = np.ceil(tri[..., 1].min(1)).clip(0, height - 1)
    ymax = np.floor(tri[..., 1].max(1)).clip(-1, height - 1)
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    keep = (
        (z > near).all(1)
        & (np.abs(det) > 1e-12)
        & (xmax >= xmin)
        & (ymax >= ymin)
        & (tri[..., 0].max(1) >= 0)
        & (tri[..., 1].max(1) >= 0)
        & (tri[..., 0].min(1) <= width - 1)
        & (tri[..., 1].min(1) <= height - 1)
    )
    ids = np.nonzero(keep)[0]
    if ids.size == 0:
        return Raster(
            fbuf.reshape(height, width), zbuf.reshape(height, width), bbuf.reshape(height, width, 3)
        )
    bw = (xmax[ids] - xmin[ids] + 1).astype(np.int64)
    bh = (ymax[ids] - ymin[ids] + 1).astype(np.int64)
    count = bw * bh
    # inverse of the 2x2 edge matrix, per triangle: (l1, l2) = inv @ (p - v0)
    inv = np.stack([e2[ids, 1], -e2[ids, 0], -e1[ids, 1], e1[ids, 0]], axis=1) / det[ids, None]
    ends = np.cumsum(count)
    start = 0
    while start < ids.size:
        # triangles [start, stop) hold at most `chunk` candidates (at least one triangle)
        base = ends[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(ends, base + chunk, side="right")))
        sel = np.arange(start, stop)
        n = count[sel]
        tid = np.repeat(sel, n)
        offset = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        px = xmin[ids[tid]] + offset % bw[tid]
        py = ymin[ids[tid]] + offset // bw[tid]
        f = ids[tid]
        dx = px - tri[f, 0, 0]
        dy = py - tri[f, 0, 1]
        l1 = inv[tid, 0] * dx + inv[tid, 1] * dy
        l2 = inv[tid, 2] * dx + inv[tid, 3] * dy
        l0 = 1.0 - l1 - l2
        inside = (l0 >= 0) & (l1 >= 0) & (l2 >= 0)
        f, px, py = f[inside], px[inside], py[inside]
        lam = np.stack([l0[inside], l1[inside], l2[inside]], axis=1) / z[f]
        inv_z = lam.sum(1)
        zc = 1.0 / inv_z
        pix = (py * width + px).astype(np.int64)
        order = np.lexsort((zc, pix))
        pix_sorted = pix[order]
        first = np.ones(order.size, dtype=bool)
        first[1:] = pix_sorted[1:] != pix_sorted[:-1]
        win = order[first]
        p = pix[win]
        nearer = zc[win] < zbuf[p]
        win, p = win[nearer], p[nearer]
        zbuf[p] = zc[win]
        fbuf[p] = f[win]
        bbuf[p] = lam[win] / inv_z[win, None]
        start = stop
    return Raster(
        fbuf.reshape(height, width), zbuf.reshape(height, width), bbuf.reshape(height, width, 3)
    )


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) unit vertex normals, the area-weighted mean of the adjacent face normals.

    Faces are taken counter-clockwise seen from outside (right-hand rule).
    """
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.maximum(norm, 1e-12)


def interpolate(raster: Raster, faces: np.ndarray, attribute: np.ndarray) -> np.ndarray:
    """Interpolate a per-vertex attribute (V, C) at the visible pixels: (H, W, C), 0 elsewhere."""
    h, w = raster.face.shape
    out = np.zeros((h, w, attribute.shape[1]))
    m = raster.mask
    tri = faces[raster.face[m]]  # (P, 3)
    out[m] = np.einsum("pk,pkc->pc", raster.bary[m], attribute[tri])
    return out


def lambert(
    albedo: np.ndarray, normals: np.ndarray, light_dir: np.ndarray, ambient: float, diffuse: float
) -> np.ndarray:
    """Lambert shading ``albedo * (ambient + diffuse * max(0, n . l))``.

    Args:
        albedo: (..., 3) colours in [0, 1].
        normals: (..., 3) unit normals, world frame.
        light_dir: (3,) unit vector towards the light.
        ambient, diffuse: light intensities.
    """
    n = normals / np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    cos = np.clip(n @ np.asarray(light_dir, dtype=np.float64), 0.0, None)
    return albedo * (ambient + diffuse * cos)[..., None]
