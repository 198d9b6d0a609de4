"""Pixel geometry of the model's contour choice (:mod:`torchfit.fit.model_contour`): which
samples lie near the rendered outline, and which way a sample's edge faces."""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from torchfit.fit.model_contour import EdgeSampler

__all__ = ["near_boundary", "outward_normals"]


def near_boundary(
    bpix: np.ndarray, ui: np.ndarray, vi: np.ndarray, size: tuple[int, int], tolerance: float
) -> np.ndarray:
    """(N,) bool: pixel (ui, vi) is within ``tolerance`` of a boundary pixel ``bpix`` (n, 2).

    Exact: the pixel offsets within ``tolerance`` (``du² + dv² <= tolerance²``, 5 of them for
    one pixel) are looked up around each query pixel in an image of the boundary pixels; the
    exact Euclidean distance transform gives the same answer at many times the cost.
    """
    near = np.zeros(ui.shape, bool)
    if not len(bpix):
        return near
    w, h = size
    r = int(np.floor(tolerance))
    boundary = np.zeros((h + 2 * r, w + 2 * r), bool)
    boundary[bpix[:, 1] + r, bpix[:, 0] + r] = True
    for a, b in _offsets(tolerance):
        near |= boundary[vi + r + b, ui + r + a]
    return near


@functools.lru_cache(maxsize=8)
def _offsets(tolerance: float) -> tuple[tuple[int, int], ...]:
    """The pixel offsets ``(du, dv)`` with ``du² + dv² <= tolerance²``."""
    r = int(np.floor(tolerance))
    span = np.arange(-r, r + 1)
    du, dv = np.meshgrid(span, span)
    within = du * du + dv * dv <= tolerance * tolerance
    return tuple(zip(du[within].tolist(), dv[within].tolist(), strict=True))


def outward_normals(sampler: EdgeSampler, px: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """(n, 2) unit outward normals of the projected edges of contour samples ``samples`` (n,).

    An edge of the outline has the triangles beside it on the silhouette's side (the two
    faces of a fold project onto the same side; a border edge has its one face there), so
    the outward normal is the edge's normal pointing away from its first face's third vertex.
    """
    e = samples // sampler.k
    a, b = sampler.edges.numpy()[e].T
    face = sampler.faces.numpy()[sampler.edge_faces.numpy()[e, 0]]
    third = face.sum(1) - a - b
    d = px[b] - px[a]
    n = np.stack([-d[:, 1], d[:, 0]], 1)
    flip = ((px[third] - px[a]) * n).sum(1) > 0
    n[flip] *= -1
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)
