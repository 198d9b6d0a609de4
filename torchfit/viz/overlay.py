"""Overlays of a fitted posture: person contour, model contour, the ignored pixels and the
bent-joint marks."""

from __future__ import annotations

import cv2
import numpy as np

from torchfit.viz.raster import draw_label, draw_polyline, outer_outlines

__all__ = ["fit_overlay"]


def fit_overlay(
    image: np.ndarray,
    person: np.ndarray,
    model_mask: np.ndarray,
    label: str,
    uncertain: np.ndarray | None = None,
    marks: list[tuple] | None = None,
) -> np.ndarray:
    """RGB overlay of one posture.

    Args:
        image: (H, W, 3) uint8 RGB.
        person: (H, W) bool, the person's silhouette (outline drawn magenta).
        model_mask: (H, W) bool, the fitted model's silhouette (outline drawn green).
        label: text drawn at the top left.
        uncertain: optional (H, W) bool, pixels the fit ignored (tinted yellow).
        marks: optional ``(target, joint)`` pixel pairs of bent-joint marks: the joint the
            person's limbs place (a magenta cross; ``None`` where not found) and the model's
            joint (a green dot).

    Returns:
        (H, W, 3) uint8 RGB.
    """
    out = image.copy()
    if uncertain is not None and uncertain.any():
        tint = np.array([255, 220, 0], dtype=np.float32)
        out[uncertain] = (0.5 * out[uncertain] + 0.5 * tint).astype(np.uint8)
    for c in outer_outlines(person):
        draw_polyline(out, c, (255, 0, 255), thickness=2)
    for c in outer_outlines(model_mask):
        draw_polyline(out, c, (0, 200, 0), thickness=2)
    for target, joint in marks or []:
        if target is not None:
            u, v = (int(round(c)) for c in target)
            cv2.drawMarker(out, (u, v), (255, 0, 255), cv2.MARKER_CROSS, 14, 2)
        u, v = (int(round(c)) for c in joint)
        cv2.circle(out, (u, v), 4, (0, 200, 0), -1)
    draw_label(out, label, (10, 28), 0.8)
    return out
