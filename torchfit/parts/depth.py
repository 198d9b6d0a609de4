"""Joint depths from the whole outline: dense silhouette matching with the aperture in mind.

Why: matching a joint's own outline anchors (:func:`torchfit.parts.correspond.corresponding_joints`)
fails where the outline runs along the epipolar line. A horizontal arm's upper and lower edges
look the same after any shift along the arm, so the best shift there is noise, and one pixel of
disparity is several centimetres of depth (the aperture problem). Here every outline point of
the left view is matched, each is weighted by how well its edge fixes a shift along its
epipolar line (``sin²`` of the angle between edge and line), and a joint's depth is the
weighted median of the depths of the outline points around it. The occluding contour of a limb
or the trunk lies at about the depth of its axis, so the outline's depth near a joint is the
joint's depth.

Then the joint is the point at that depth (left camera frame) on the mean of the two views'
labelled viewing rays.

Conventions: masks ``(H, W)`` bool; points ``(u, v)`` pixels (``v`` down); depths are
left-camera ``z``, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from torchfit.camera import Camera
from torchfit.parts.correspond import epipolar_lines, match_point, smooth_mask
from torchfit.parts.stereo import pixel_rays, triangulate_midpoint

__all__ = [
    "OutlineDepth",
    "outline_depths",
    "weighted_median",
    "local_plane_depth",
    "joints_at_depth",
]


@dataclass
class OutlineDepth:
    """Matched outline points of the left view.

    Attributes:
        points: ``(N, 2)`` left pixels.
        depths: ``(N,)`` left-camera depth of each matched point, metres.
        weights: ``(N,)`` ``sin²`` of the angle between the outline and the epipolar line,
            zeroed where the match is poor.
    """

    points: np.ndarray
    depths: np.ndarray
    weights: np.ndarray


def _outline(mask: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``step`` pixels along the largest outer contour and unit tangents there."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros((0, 2)), np.zeros((0, 2))
    c = max(contours, key=len)[:, 0, :].astype(np.float64)
    k = 3  # tangent from +-k contour pixels
    tangent = np.roll(c, -k, axis=0) - np.roll(c, k, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    return c[::step], tangent[::step]


def _camera_depths(points3d: torch.Tensor, camera: Camera) -> np.ndarray:
    """``(N,)`` camera-frame ``z`` of ``(N, 3)`` world points."""
    R, t = camera.R[0].to(points3d), camera.t[0].to(points3d)
    return (points3d @ R.T + t)[:, 2].numpy()


def outline_depths(
    mask_left: np.ndarray,
    mask_right: np.ndarray,
    guess: np.ndarray,
    camera_left: Camera,
    camera_right: Camera,
    step_px: int = 3,
    radius_px: float = 6.0,
    search_px: float = 8.0,
    min_sine: float = 0.5,
    max_cost: float = 0.02,
) -> OutlineDepth:
    """Depths of the left outline by matching the smoothed silhouettes along epipolar lines.

    Args:
        mask_left, mask_right: ``(H, W)`` bool silhouettes, holes filled.
        guess: ``(2,)`` typical right-minus-left pixel offset (e.g. the median over the
            labelled joints); the search is ``+- search_px`` around it.
        camera_left, camera_right: the calibrated pair (B = 1).
        step_px: outline sampling.
        radius_px: matching window half-size.
        search_px: search range along the line, pixels.
        min_sine: outline points whose edge is within ``asin(min_sine)`` of the epipolar line
            are not matched (weight 0).
        max_cost: a match whose mean squared window difference exceeds this (the silhouettes
            are in [0, 1]) gets weight 0: an edge seen in one view only.

    Returns:
        An :class:`OutlineDepth` (empty when the mask has no outline).
    """
    points, tangent = _outline(mask_left, step_px)
    if len(points) == 0:
        return OutlineDepth(points, np.zeros(0), np.zeros(0))
    q_c, e, _ = epipolar_lines(
        points, points + np.asarray(guess, float)[None], camera_left, camera_right
    )
    sine2 = (tangent[:, 0] * e[:, 1] - tangent[:, 1] * e[:, 0]) ** 2
    keep = sine2 >= min_sine**2
    sl, sr = smooth_mask(mask_left), smooth_mask(mask_right)
    matched = q_c.copy()
    weights = np.where(keep, sine2, 0.0)
    for i in np.flatnonzero(keep):
        q, cost = match_point(sl, sr, points[i], q_c[i], e[i], radius_px, search_px)
        matched[i] = q
        if cost > max_cost:
            weights[i] = 0.0
    x, _ = triangulate_midpoint(
        torch.from_numpy(points)[None], camera_left, torch.from_numpy(matched)[None], camera_right
    )
    depths = _camera_depths(x[0], camera_left)
    weights = np.where(np.isfinite(depths), weights, 0.0)
    return OutlineDepth(points, np.nan_to_num(depths), weights)


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The weighted median (NaN when all weights are zero)."""
    keep = weights > 0
    if not keep.any():
        return float("nan")
    v, w = values[keep], weights[keep]
    order = np.argsort(v)
    cum = np.cumsum(w[order])
    return float(v[order][np.searchsorted(cum, 0.5 * cum[-1])])


def local_plane_depth(
    points: np.ndarray,
    depths: np.ndarray,
    weights: np.ndarray,
    at: np.ndarray,
    iterations: int = 10,
) -> float:
    """Depth at pixel ``at`` of a weighted, robust plane ``z = a + b u + c v`` through the
    outline depths.

    Iteratively reweighted least squares with Tukey's biweight on the residuals (scale:
    1.4826 times their weighted median absolute deviation), starting from the weighted
    median, so a stretch of badly matched outline does not tilt the plane. Falls back to the
    weighted median when fewer than three points carry weight.

    Args:
        points: ``(N, 2)`` pixels; depths: ``(N,)``; weights: ``(N,)`` >= 0.
        at: ``(2,)`` pixel where the depth is wanted.

    Returns:
        The depth (NaN when all weights are zero).
    """
    z0 = weighted_median(depths, weights)
    keep = weights > 0
    if keep.sum() < 3 or not np.isfinite(z0):
        return z0
    p, z, w = points[keep] - at[None], depths[keep], weights[keep]
    A = np.column_stack([np.ones(len(p)), p])
    residual = z - z0
    for _ in range(iterations):
        scale = 1.4826 * weighted_median(np.abs(residual), w)
        u = residual / max(4.685 * scale, 1e-9)
        robust = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)
        ww = w * robust
        if (ww > 0).sum() < 3:
            break
        sw = np.sqrt(ww)
        coef, *_ = np.linalg.lstsq(A * sw[:, None], z * sw, rcond=None)
        residual = z - A @ coef
    else:
        return float(coef[0])
    return z0


def joints_at_depth(
    outline: OutlineDepth,
    joints_left: dict[str, np.ndarray],
    joints_right: dict[str, np.ndarray],
    camera_left: Camera,
    camera_right: Camera,
    sigma_px: float,
) -> tuple[dict[str, list[float]], dict[str, float]]:
    """3-D joints: each at the outline's local depth, on its two labelled rays.

    The depth of joint ``j`` is that of a robust plane through the outline depths
    (:func:`local_plane_depth`), with weights ``w_i exp(-|p_i - j|² / 2 sigma²)``: the
    camera looks down on the person, so depth changes with height. The joint is the mean of
    the left ray's and the right ray's points at that left-camera depth.

    Args:
        outline: :func:`outline_depths` of the pair.
        joints_left, joints_right: joint name -> ``(2,)`` labelled pixels.
        camera_left, camera_right: the calibrated pair (B = 1).
        sigma_px: neighbourhood of a joint on the outline, pixels.

    Returns:
        ``(joints, spread)``: name -> ``[x, y, z]`` world metres, and name -> the distance
        between the two rays' points at that depth (metres; large when the labels disagree).
        A joint without matched outline points near it is left out.
    """
    R = camera_left.R[0].double()
    t = camera_left.t[0].double()
    joints: dict[str, list[float]] = {}
    spread: dict[str, float] = {}
    for name, pl in joints_left.items():
        if name not in joints_right:
            continue
        d2 = ((outline.points - pl[None]) ** 2).sum(1)
        z = local_plane_depth(
            outline.points,
            outline.depths,
            outline.weights * np.exp(-0.5 * d2 / sigma_px**2),
            np.asarray(pl, dtype=np.float64),
        )
        if not np.isfinite(z):
            continue
        ends = []
        for pix, cam in ((pl, camera_left), (joints_right[name], camera_right)):
            o, d = pixel_rays(torch.tensor(pix, dtype=torch.float64)[None, None], cam)
            o_c, d_c = R @ o[0, 0] + t, R @ d[0, 0]  # ray in the left camera frame
            ends.append(o[0, 0] + d[0, 0] * (z - o_c[2]) / d_c[2])
        joints[name] = [float(v) for v in 0.5 * (ends[0] + ends[1])]
        spread[name] = float(torch.linalg.vector_norm(ends[0] - ends[1]))
    return joints, spread
