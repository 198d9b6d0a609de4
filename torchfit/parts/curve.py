"""Closed silhouette contour → periodic cubic B-spline → analytic curvature → extrema.

The second paper (Jaume-i-Capó et al. 2012, section 2.2) interpolates the outer contour of a
silhouette with a cubic B-spline, computes the curvature analytically from the spline's first
and second derivatives, and cuts the shape at the negative curvature minima (Hoffman and
Richards' minima rule).

Conventions:

- Points are ``(u, v)`` pixels: pixel ``(0, 0)`` is the centre of the top-left pixel, ``u``
  grows to the right and ``v`` **down** (design.md section 2).
- Curvature is in 1/pixels and its sign is **orientation free**: positive where the outline
  bulges outwards (convex: head top, hands, feet, the outer elbow), negative where it is
  concave (neck sides, armpits, the crotch), whichever way the contour runs and even though the
  image ``v`` axis points down. Formally ``kappa = s (x' y'' - y' x'') / |c'|^3`` with
  ``s = sign`` of the contour's signed (shoelace) area in the same ``(u, v)`` coordinates.
- The spline parameter ``t`` runs over ``[0, 1)`` once around the contour (chord-length
  parameterisation), so contour positions are compared modulo 1.

The spline is fitted with FITPACK (``scipy.interpolate.splprep`` with ``per=1``). ``smoothing``
is the allowed RMS distance, in pixels, between the spline and the contour points: 0 gives the
paper's exact interpolation, about 1 pixel removes the staircase of a pixel contour.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.interpolate import splev, splprep

from torchfit.parts.errors import PartsError

__all__ = [
    "ContourSpline",
    "CurvatureExtremum",
    "fit_contour_spline",
    "curvature_extrema",
]


@dataclass
class ContourSpline:
    """A closed periodic cubic B-spline through a silhouette contour.

    Attributes:
        tck: FITPACK representation ``(knots, [coeffs_u, coeffs_v], 3)``.
        length: arc length of the spline in pixels (from a dense sampling).
        orientation: ``+1`` or ``-1``, the sign of the signed area of the contour in ``(u, v)``
            coordinates; it makes :meth:`curvature` positive on convex parts.
        n_points: number of contour points the spline was fitted to.
    """

    tck: tuple
    length: float
    orientation: float
    n_points: int

    def point(self, t: np.ndarray | float) -> np.ndarray:
        """Positions on the curve.

        Args:
            t: ``(M,)`` parameters (any real values; taken modulo 1).

        Returns:
            ``(M, 2)`` ``(u, v)`` pixels.
        """
        t = np.mod(np.atleast_1d(np.asarray(t, dtype=np.float64)), 1.0)
        return np.stack(splev(t, self.tck), axis=-1)

    def derivatives(self, t: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """First and second derivatives with respect to ``t``.

        Args:
            t: ``(M,)`` parameters.

        Returns:
            ``(d1, d2)``, each ``(M, 2)`` in pixels per unit parameter (squared for ``d2``).
        """
        t = np.mod(np.atleast_1d(np.asarray(t, dtype=np.float64)), 1.0)
        d1 = np.stack(splev(t, self.tck, der=1), axis=-1)
        d2 = np.stack(splev(t, self.tck, der=2), axis=-1)
        return d1, d2

    def curvature(self, t: np.ndarray | float) -> np.ndarray:
        """Signed curvature (1/pixels), positive on convex parts of the outline.

        Args:
            t: ``(M,)`` parameters.

        Returns:
            ``(M,)`` curvature values.
        """
        d1, d2 = self.derivatives(t)
        cross = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
        speed = np.maximum(np.hypot(d1[:, 0], d1[:, 1]), 1e-12)
        return self.orientation * cross / speed**3

    def normal(self, t: np.ndarray | float) -> np.ndarray:
        """Unit normals pointing into the silhouette.

        Args:
            t: ``(M,)`` parameters.

        Returns:
            ``(M, 2)`` unit vectors ``(du, dv)``.
        """
        d1, _ = self.derivatives(t)
        tangent = d1 / np.maximum(np.linalg.norm(d1, axis=1, keepdims=True), 1e-12)
        # In (u, v) coordinates rotating the tangent by +90 degrees, (-dv, du), points to the
        # left of the direction of travel, which is the inside for a positive signed area.
        return self.orientation * np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)

    def sample(self, spacing_px: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Parameters and points about ``spacing_px`` apart along the curve.

        Returns:
            ``(t, points)``: ``(M,)`` parameters in ``[0, 1)`` and ``(M, 2)`` pixels.
        """
        m = max(int(np.ceil(self.length / max(spacing_px, 1e-3))), 8)
        t = np.arange(m, dtype=np.float64) / m
        return t, self.point(t)


@dataclass
class CurvatureExtremum:
    """One significant curvature extremum of a contour spline.

    Attributes:
        t: spline parameter in ``[0, 1)``.
        point: ``(2,)`` ``(u, v)`` pixels.
        curvature: signed curvature there (1/pixels); negative for a minimum.
        kind: ``"min"`` (negative minimum, a concavity) or ``"max"`` (positive maximum).
    """

    t: float
    point: np.ndarray
    curvature: float
    kind: str


def _clean_points(points: np.ndarray) -> np.ndarray:
    """Drop consecutive duplicates (also across the wrap) of an ordered contour."""
    keep = np.any(points != np.roll(points, 1, axis=0), axis=1)
    if not keep.any():
        return points[:1]
    return points[keep]


def fit_contour_spline(
    points: np.ndarray | torch.Tensor,
    smoothing: float = 1.0,
    point_spacing: int = 1,
) -> ContourSpline:
    """Fit a periodic cubic B-spline to an ordered closed contour.

    Args:
        points: ``(N, 2)`` ordered ``(u, v)`` contour pixels, as
            :func:`torchfit.image.trace_outer_contour` returns them (the first point is not
            repeated at the end).
        smoothing: allowed RMS distance between spline and points, pixels (``>= 0``; 0
            interpolates every point, as the paper does).
        point_spacing: use every ``point_spacing``-th contour point (``>= 1``).

    Returns:
        The :class:`ContourSpline`.

    Raises:
        PartsError: ``points`` is not ``(N, 2)``, has fewer than 8 distinct points, or an
            option is out of range.
    """
    if isinstance(points, torch.Tensor):
        points = points.detach().cpu().numpy()
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise PartsError(f"points: expected shape (N, 2), got {points.shape}")
    if smoothing < 0:
        raise PartsError(f"smoothing: expected >= 0 pixels, got {smoothing}")
    if point_spacing < 1:
        raise PartsError(f"point_spacing: expected an integer >= 1, got {point_spacing}")
    pts = _clean_points(points)[::point_spacing]
    if len(pts) < 8:
        raise PartsError(f"points: expected at least 8 distinct contour points, got {len(pts)}")
    closed = np.concatenate([pts, pts[:1]], axis=0)
    # Chord-length parameter; FITPACK's per=1 ignores the value of the repeated last point.
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    u = np.concatenate([[0.0], np.cumsum(seg)])
    u /= u[-1]
    s = float(len(pts)) * smoothing**2
    tck, _ = splprep([closed[:, 0], closed[:, 1]], u=u, s=s, per=1, k=3, quiet=1)
    x, y = pts[:, 0], pts[:, 1]
    area = 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    orientation = 1.0 if area >= 0 else -1.0
    dense = np.stack(splev(np.linspace(0.0, 1.0, 8 * len(pts) + 1), tck), axis=-1)
    length = float(np.linalg.norm(np.diff(dense, axis=0), axis=1).sum())
    return ContourSpline(tck=tck, length=length, orientation=orientation, n_points=len(pts))


def curvature_extrema(
    spline: ContourSpline,
    min_curvature: float,
    min_separation_px: float = 10.0,
    spacing_px: float = 0.5,
) -> list[CurvatureExtremum]:
    """Significant negative curvature minima and positive curvature maxima of a spline.

    A sample is a negative minimum when its curvature is below ``-min_curvature`` and is the
    smallest within ``min_separation_px`` of arc length on either side (a positive maximum:
    above ``+min_curvature`` and the largest). Ties keep the first sample.

    Args:
        spline: from :func:`fit_contour_spline`.
        min_curvature: significance threshold, 1/pixels (``> 0``).
        min_separation_px: half-width of the suppression window along the curve, pixels.
        spacing_px: sampling step along the curve, pixels.

    Returns:
        Extrema sorted by ``t``.

    Raises:
        PartsError: a threshold or spacing is not positive.
    """
    if min_curvature <= 0:
        raise PartsError(f"min_curvature: expected > 0 (1/pixels), got {min_curvature}")
    if spacing_px <= 0 or min_separation_px <= 0:
        raise PartsError(
            f"spacing_px, min_separation_px: expected > 0, got {spacing_px}, {min_separation_px}"
        )
    t, pts = spline.sample(spacing_px)
    kappa = spline.curvature(t)
    m = len(t)
    half = max(int(round(min_separation_px / (spline.length / m))), 1)
    half = min(half, (m - 1) // 2)
    # Sliding window extremes over the periodic sequence.
    idx = (np.arange(m)[:, None] + np.arange(-half, half + 1)[None, :]) % m
    window = kappa[idx]
    out: list[CurvatureExtremum] = []
    for kind, extreme, sign in (
        ("min", window.min(axis=1), -1.0),
        ("max", window.max(axis=1), 1.0),
    ):
        # An extremum is significant, extreme in its window, and (for plateaus of equal values)
        # the first such sample of its window.
        first = np.argmax(window == extreme[:, None], axis=1) == half
        mask = (sign * kappa > min_curvature) & (kappa == extreme) & first
        for i in np.flatnonzero(mask):
            out.append(CurvatureExtremum(float(t[i]), pts[i].copy(), float(kappa[i]), kind))
    out.sort(key=lambda e: e.t)
    return out
