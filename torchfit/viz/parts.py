"""Overlay drawings of a labelling: spline, extrema, cuts, joints, hand ellipses.

Colours (RGB): spline green, negative minima red circles, positive maxima blue circles, cuts
yellow lines, joints magenta crosses with their names, hand ellipses light blue. Images
``(H, W, 3)`` ``uint8`` RGB; points ``(u, v)`` pixels.
"""

from __future__ import annotations

import cv2
import numpy as np

from torchfit.parts.rules import Labelling

__all__ = ["draw_labelling"]

_SHIFT = 4  # cv2 sub-pixel drawing: coordinates * 16


def _pt(p: np.ndarray) -> tuple[int, int]:
    return int(round(float(p[0]) * (1 << _SHIFT))), int(round(float(p[1]) * (1 << _SHIFT)))


def draw_labelling(
    image: np.ndarray,
    labelling: Labelling,
    mask: np.ndarray | None = None,
    truth: dict[str, np.ndarray] | None = None,
    scale: int = 2,
) -> np.ndarray:
    """Draw a labelling over its image (upscaled by ``scale`` so that the marks stay readable).

    Args:
        image: ``(H, W, 3)`` uint8 RGB.
        labelling: from :func:`torchfit.parts.decompose_cactus`.
        mask: ``(H, W)`` silhouette, lightened in the drawing when given.
        truth: joint name -> ``(2,)`` true pixels, drawn as small white crosses.
        scale: integer upscaling factor.

    Returns:
        ``(scale H, scale W, 3)`` uint8 RGB; the status is written in the top-left corner.
    """
    out = image.astype(np.float32)
    if mask is not None:
        out[mask] = 0.65 * out[mask] + 0.35 * 255
    out = out.astype(np.uint8)
    out = cv2.resize(out, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    s = float(scale)

    def sp(p: np.ndarray) -> tuple[int, int]:
        return _pt((np.asarray(p, dtype=np.float64) + 0.5) * s - 0.5)

    lt = cv2.LINE_AA
    if labelling.spline is not None:
        _, pts = labelling.spline.sample(1.0)
        poly = np.array([sp(p) for p in pts], dtype=np.int32)
        cv2.polylines(out, [poly], True, (0, 200, 0), 1, lt, _SHIFT)
    for e in labelling.extrema:
        colour = (230, 0, 0) if e.kind == "min" else (0, 80, 255)
        cv2.circle(out, sp(e.point), int(3 * s) << _SHIFT, colour, 1, lt, _SHIFT)
    for cut in labelling.cuts.values():
        cv2.line(out, sp(cut.a), sp(cut.b), (255, 220, 0), 1, lt, _SHIFT)
    for ellipse in labelling.hands.values():
        major, minor, angle = ellipse.axes()
        centre = tuple(float(c) for c in (ellipse.centre + 0.5) * s - 0.5)
        box = (centre, (2 * major * s, 2 * minor * s), angle)
        cv2.ellipse(out, box, (0, 160, 255), 2, lt)
    if truth:
        for p in truth.values():
            x, y = ((np.asarray(p) + 0.5) * s - 0.5).round().astype(int)
            cv2.drawMarker(out, (int(x), int(y)), (255, 255, 255), cv2.MARKER_TILTED_CROSS, 7, 1)
    for name, p in labelling.joints.items():
        x, y = ((np.asarray(p) + 0.5) * s - 0.5).round().astype(int)
        cv2.drawMarker(out, (int(x), int(y)), (255, 0, 255), cv2.MARKER_CROSS, 9, 2)
        cv2.putText(
            out,
            name,
            (int(x) + 5, int(y) - 5),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.35 * s / 2,
            (255, 0, 255),
            1,
            lt,
        )
    text = "ok" if labelling.ok else f"FAILED {labelling.failed_rule}: {labelling.message}"
    cv2.putText(out, text[:90], (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 0, 0), 1, lt)
    return out
