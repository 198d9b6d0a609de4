"""A bent joint's pixel from the axes of the two limbs it joins, on a silhouette.

Where a limb is bent (the flexed knee of posture 3, an elbow of posture 5), the silhouette shows
both limbs as bands. Each band's axis is the line through the midpoints of its cross-sections;
the two axes cross near the joint. Cross-sections are taken away from both ends of a limb
(where the bands merge with the joint's flesh, the trunk or a hand), so the estimate rests on
the limbs' straight runs and not on the shape of the flesh at the bend.

The crossing is not the joint centre itself (a calf bulges behind the shank's bone): the fit
compares a person's crossing with its own model's, measured on the model's silhouette in the
same way (:mod:`torchfit.fit.bends`).

Conventions as :mod:`torchfit.image.contours`: masks ``(H, W)`` bool (``True`` = person), pixel
``(0, 0)`` the centre of the top-left pixel, points ``(u, v)`` with ``v`` down, pixels.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from torchfit.errors import ShapeError

__all__ = ["LimbAxis", "Crossing", "limb_axis", "crossing"]

#: Step along a cross-section, pixels.
_STEP = 0.5


class LimbAxis(NamedTuple):
    """A limb's band on a silhouette: a point on its axis, the axis' unit direction and the
    band's median width (pixels, over the sections that made the axis)."""

    point: np.ndarray
    direction: np.ndarray
    width: float


class Crossing(NamedTuple):
    """Where the axes of the two limbs at a bent joint cross (pixels), with the two axes."""

    point: np.ndarray
    upper: LimbAxis
    lower: LimbAxis


def _section_runs(
    mask: np.ndarray, centres: np.ndarray, normal: np.ndarray, reach: float
) -> np.ndarray:
    """(n, 3): midpoint (u, v) and length of the run of person pixels along ``normal``
    through each centre (the run holding the centre, else the nearest one within ``reach``);
    NaN where there is none or the run reaches the image frame or ``reach``."""
    h, w = mask.shape
    offsets = np.arange(-reach, reach + _STEP / 2, _STEP)  # (m,)
    pts = centres[:, None, :] + offsets[None, :, None] * normal  # (n, m, 2)
    u = np.rint(pts[..., 0]).astype(np.int64)
    v = np.rint(pts[..., 1]).astype(np.int64)
    in_frame = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    inside = np.zeros(u.shape, bool)
    inside[in_frame] = mask[v[in_frame], u[in_frame]]
    out = np.full((len(centres), 3), np.nan)
    mid = len(offsets) // 2
    for i in range(len(centres)):
        row = inside[i]
        hits = np.flatnonzero(row)
        if not len(hits):
            continue
        seed = hits[np.argmin(np.abs(hits - mid))]
        lo, hi = seed, seed
        while lo > 0 and row[lo - 1]:
            lo -= 1
        while hi < len(row) - 1 and row[hi + 1]:
            hi += 1
        # a run cut by the line's ends or the image frame has no known extent
        if lo == 0 or hi == len(row) - 1 or not (in_frame[i, lo - 1] and in_frame[i, hi + 1]):
            continue
        out[i, :2] = centres[i] + 0.5 * (offsets[lo] + offsets[hi]) * normal
        out[i, 2] = offsets[hi] - offsets[lo] + _STEP
    return out


def limb_axis(
    mask: np.ndarray,
    start: np.ndarray,
    end: np.ndarray,
    span: tuple[float, float],
    sections: int = 9,
    min_sections: int = 5,
    max_bend: float = 0.08,
    max_width_change: float = 0.25,
    max_left_out: int = 2,
) -> LimbAxis | None:
    """The axis of the band of person pixels along the segment ``start`` → ``end``.

    A few cross-sections may be spoilt (a shadow's bite out of the band, a run that crosses
    into a neighbouring limb, a hole where the person's colour matches the room): sections
    whose width is more than ``max_width_change`` off the median width are left out, then the
    section furthest from the axis, one at a time, while it is further than the band allows.
    At most ``max_left_out`` sections go: trimmed further, any band would line up somewhere,
    and the axis would be made by a bare majority of its sections.

    Args:
        mask: (H, W) bool silhouette.
        start, end: (2,) pixels: the limb's guessed ends (e.g. the model's projected joints).
        span: (t0, t1), the part of the segment whose cross-sections count (fractions of its
            length from ``start``).
        sections: how many cross-sections, evenly spaced over ``span``.
        min_sections: the fewest cross-sections, complete runs of person pixels that line up,
            that make an axis.
        max_bend: the largest distance of a section's midpoint from the axis, as a fraction
            of the median section (at least 1.5 px): a band whose midpoints do not lie on a
            line is not one limb (a silhouette with a hole, a hand against the thigh).
        max_width_change: the largest relative difference of a section's width from the
            median width of the sections.
        max_left_out: the most sections (of those found) left out of the axis.

    Returns:
        The :class:`LimbAxis` (its direction pointing from ``start`` towards ``end``), or
        ``None`` where fewer than ``min_sections`` sections are found, or they do not line up
        with at most ``max_left_out`` of them left out.
    """
    if mask.ndim != 2:
        raise ShapeError(f"mask: expected (H, W), got shape {tuple(mask.shape)}")
    start, end = np.asarray(start, float), np.asarray(end, float)
    along = end - start
    length = float(np.hypot(*along))
    if not math.isfinite(length) or length < 4.0:
        return None
    d = along / length
    normal = np.array([-d[1], d[0]])
    t = np.linspace(span[0], span[1], sections)
    runs = _section_runs(mask, start + t[:, None] * along, normal, 0.5 * length)
    runs = runs[np.isfinite(runs[:, 0])]
    if len(runs) < min_sections:
        return None
    found = len(runs)
    width = float(np.median(runs[:, 2]))
    runs = runs[np.abs(runs[:, 2] - width) <= max_width_change * width]
    while len(runs) >= max(min_sections, found - max_left_out):
        mids = runs[:, :2]
        centre = mids.mean(0)
        direction = np.linalg.svd(mids - centre)[2][0]
        off_axis = np.abs((mids - centre) @ np.array([-direction[1], direction[0]]))
        width = float(np.median(runs[:, 2]))
        if off_axis.max() <= max(1.5, max_bend * width):
            return LimbAxis(centre, direction if direction @ d >= 0 else -direction, width)
        runs = np.delete(runs, int(np.argmax(off_axis)), 0)
    return None


def crossing(
    mask: np.ndarray,
    proximal: np.ndarray,
    joint: np.ndarray,
    distal: np.ndarray,
    min_angle_deg: float = 30.0,
) -> Crossing | None:
    """Where the axes of the limbs ``proximal`` → ``joint`` and ``joint`` → ``distal`` cross.

    Args:
        mask: (H, W) bool silhouette.
        proximal, joint, distal: (2,) pixels: guesses of the three joints (e.g. hip, knee and
            ankle of the model as it stands).
        min_angle_deg: the smallest bend (angle between the two axes) that places the joint;
            nearly straight limbs cross anywhere along them.

    Returns:
        The :class:`Crossing`, or ``None`` where an axis is not found or the bend is too
        small.
    """
    upper = limb_axis(mask, proximal, joint, (0.3, 0.75))
    lower = limb_axis(mask, joint, distal, (0.3, 0.7))
    if upper is None or lower is None:
        return None
    (p1, d1, _), (p2, d2, _) = upper, lower
    sin = abs(d1[0] * d2[1] - d1[1] * d2[0])
    if sin < math.sin(math.radians(min_angle_deg)):
        return None
    a, _ = np.linalg.solve(np.stack([d1, -d2], 1), p2 - p1)
    return Crossing(p1 + a * d1, upper, lower)
