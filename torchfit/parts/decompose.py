"""One posture-5 silhouette → labelled 2-D joints: contour, spline, extrema, rules, wrists.

Conventions: masks ``(H, W)`` bool (``True`` = person), images ``(H, W, 3)`` ``uint8`` RGB,
points ``(u, v)`` pixels with ``v`` down (design.md section 2).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from torchfit.image.contours import trace_outer_contour
from torchfit.image.morphology import fill_holes
from torchfit.parts.curve import curvature_extrema, fit_contour_spline
from torchfit.parts.errors import PartsError
from torchfit.parts.options import PartsOptions
from torchfit.parts.rules import JointOffsets, Labelling, RuleFailure, label_cactus
from torchfit.parts.wrists import find_wrists

__all__ = ["offsets_from_options", "leg_gap_top", "decompose_cactus"]


def leg_gap_top(mask: np.ndarray, filled: np.ndarray, min_area: float = 0.002) -> np.ndarray | None:
    """The top of the gap between the legs where it is a hole of the silhouette.

    A floor shadow (or touching feet) can close the gap between the legs into a hole; the
    crotch is then not on the outer contour but is the highest point of that hole. The hole
    taken is the largest one whose top lies in the lower half of the silhouette.

    Args:
        mask: ``(H, W)`` bool silhouette, holes not filled.
        filled: the same with its holes filled (:func:`torchfit.image.morphology.fill_holes`).
        min_area: smallest hole area, as a fraction of the silhouette height squared.

    Returns:
        ``(2,)`` ``(u, v)`` pixels (the middle of the hole's top row), or None.
    """
    holes = (filled & ~mask).astype(np.uint8)
    if not holes.any():
        return None
    rows = np.nonzero(filled.any(axis=1))[0]
    top, bottom = rows[0], rows[-1]
    middle = 0.5 * (top + bottom)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(holes, connectivity=4)
    best, best_area = None, min_area * float(bottom - top) ** 2
    for k in range(1, n):
        area = stats[k, cv2.CC_STAT_AREA]
        if stats[k, cv2.CC_STAT_TOP] > middle and area >= best_area:
            best, best_area = k, area
    if best is None:
        return None
    v = stats[best, cv2.CC_STAT_TOP]
    us = np.nonzero(labels[v] == best)[0]
    return np.array([float(us.mean()), float(v) - 0.5])


def offsets_from_options(config: PartsOptions) -> JointOffsets:
    """The :class:`JointOffsets` of a :class:`~torchfit.parts.PartsOptions`."""

    def pair(name: str) -> tuple[float, float]:
        value = getattr(config, f"offset_{name}")
        if len(value) != 2:
            raise PartsError(f"parts.offset_{name}: expected [down, out], got {value!r}")
        return float(value[0]), float(value[1])

    return JointOffsets(*(pair(n) for n in ("back", "neck", "shoulder", "elbow", "wrist")))


def _as_numpy(x: np.ndarray | torch.Tensor) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def decompose_cactus(
    mask: np.ndarray | torch.Tensor,
    image: np.ndarray | torch.Tensor | None = None,
    config: PartsOptions | None = None,
) -> Labelling:
    """Label the joints of a person in posture 5 from its silhouette (and image, for wrists).

    Args:
        mask: ``(H, W)`` silhouette, non-zero = person (one region). Leave its holes
            unfilled: a hole between the legs (a floor shadow joining the feet) gives the
            crotch (:func:`leg_gap_top`); the outline is taken from the filled mask.
        image: ``(H, W, 3)`` ``uint8`` RGB of the same view, for the wrists; None skips them.
        config: options (defaults when None); ``config.wrists = False`` skips the wrists.

    Returns:
        A :class:`~torchfit.parts.rules.Labelling`: ``status == "ok"`` with ``back``, ``neck``,
        shoulders, elbows (and wrists) in pixels, or ``"failed"`` naming the failed rule
        (``"contour"`` when the mask has no usable outline).

    Raises:
        PartsError: ``mask`` is not 2-D or ``image`` does not match it.
    """
    config = config or PartsOptions()
    mask = _as_numpy(mask)
    if mask.ndim != 2:
        raise PartsError(f"mask: expected shape (H, W), got {mask.shape}")
    mask = mask != 0
    if image is not None:
        image = _as_numpy(image)
        if image.shape != (*mask.shape, 3):
            raise PartsError(
                f"image: expected shape {(*mask.shape, 3)} (H, W, 3) like the mask, "
                f"got {image.shape}"
            )
    filled = fill_holes(mask)
    contour = trace_outer_contour(filled).numpy()
    if len(contour) < 50:
        return Labelling(
            failed_rule="contour", message=f"the silhouette outline has {len(contour)} pixels"
        )
    height = float(np.ptp(contour[:, 1])) + 1.0
    spline = fit_contour_spline(contour, config.smoothing_px, config.point_spacing)
    extrema = curvature_extrema(
        spline, config.min_curvature / height, max(config.min_separation * height, 1.0)
    )
    centre_u = float(np.nonzero(mask)[1].mean())
    offsets = offsets_from_options(config)
    result = label_cactus(spline, extrema, centre_u, config.hand_exclusion)
    if result.ok and config.wrists and image is not None:
        try:
            result.hands = find_wrists(
                image, mask, result, config.skin_threshold, config.hand_start, config.face_band
            )
        except RuleFailure as failure:
            result.fail(failure)
    if result.ok:
        offsets.apply(result)
    return result
