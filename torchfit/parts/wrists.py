"""Wrists from hand colour (second paper, section 2.3, last paragraph).

The outline has no concavity at the wrist, so the paper finds the hands by colour: the hand is
approximated by an ellipse fitted to skin-coloured pixels, and the wrist is where the line from
the elbow to the hand centre enters that ellipse.

Skin colour is learnt per image from the face: the silhouette pixels above the neck cut and
below the hair (the lower part of the head, ``face_band`` of the way from the neck cut to the
top of the head) give the mean and covariance of the chromaticity ``(r, g) = (R, G) / (R + G
+ B)``, which does not change with shading. A hand pixel is a silhouette pixel in the hand
end of the forearm (more than ``hand_start`` of the way from the elbow to the hand tip) whose
Mahalanobis distance to that model is below ``skin_threshold``. The largest 8-connected group of
them is the hand; its ellipse has the same centroid and second moments (semi-axes ``2 sigma``,
exact for a uniformly filled ellipse).

Conventions: images ``(H, W, 3)`` ``uint8`` RGB, masks ``(H, W)`` bool, points ``(u, v)``
pixels with ``v`` down.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from torchfit.parts.rules import Labelling, RuleFailure

__all__ = ["Ellipse", "SkinModel", "skin_model_from_face", "hand_ellipse", "find_wrists"]


@dataclass
class Ellipse:
    """An ellipse ``{x : (x - centre)^T cov^-1 (x - centre) = 4}`` (semi-axes ``2 sigma``).

    Attributes:
        centre: ``(2,)`` pixels.
        cov: ``(2, 2)`` second moments of the pixels it was fitted to, pixels².
        n_pixels: how many pixels.
    """

    centre: np.ndarray
    cov: np.ndarray
    n_pixels: int

    def boundary_towards(self, point: np.ndarray) -> np.ndarray:
        """``(2,)`` where the ray from the centre towards ``point`` leaves the ellipse."""
        d = np.asarray(point, dtype=np.float64) - self.centre
        norm = float(np.linalg.norm(d))
        if norm < 1e-9:
            return self.centre.copy()
        d = d / norm
        q = float(d @ np.linalg.solve(self.cov, d))
        return self.centre + (2.0 / np.sqrt(max(q, 1e-12))) * d

    def axes(self) -> tuple[float, float, float]:
        """Semi-axes (major, minor) in pixels and the major axis angle in degrees."""
        w, v = np.linalg.eigh(self.cov)
        angle = float(np.degrees(np.arctan2(v[1, 1], v[0, 1])))
        return 2.0 * float(np.sqrt(max(w[1], 0.0))), 2.0 * float(np.sqrt(max(w[0], 0.0))), angle


@dataclass
class SkinModel:
    """Gaussian skin model in chromaticity ``(r, g)``.

    Attributes:
        mean: ``(2,)``.
        cov: ``(2, 2)`` (regularised).
        n_pixels: face pixels it was learnt from.
    """

    mean: np.ndarray
    cov: np.ndarray
    n_pixels: int

    def distance(self, rgb: np.ndarray) -> np.ndarray:
        """Mahalanobis distance of ``(N, 3)`` RGB pixels to the model, ``(N,)``."""
        x = _chroma(rgb) - self.mean
        return np.sqrt(np.einsum("ni,ij,nj->n", x, np.linalg.inv(self.cov), x))


def _chroma(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb, dtype=np.float64)
    s = np.maximum(rgb.sum(axis=-1, keepdims=True), 1.0)
    return rgb[..., :2] / s


def skin_model_from_face(
    image: np.ndarray, mask: np.ndarray, labelling: Labelling, face_band: float = 0.45
) -> SkinModel:
    """Learn the skin colour from the face between the neck cut and the hair.

    Args:
        image: ``(H, W, 3)`` uint8 RGB.
        mask: ``(H, W)`` bool silhouette.
        labelling: with the ``neck`` cut and the ``head_top`` landmark.
        face_band: use the part of the head from the neck cut up to this fraction of the way
            to the top of the head.

    Raises:
        RuleFailure: ``"wrist"`` when fewer than 20 face pixels are found.
    """
    neck = labelling.cuts["neck"]
    top_v = float(labelling.landmarks["head_top"][1])
    base_v = float(neck.middle[1])
    u0, u1 = sorted((float(neck.a[0]), float(neck.b[0])))
    vv, uu = np.nonzero(mask)
    sel = (vv < base_v) & (vv > base_v - face_band * (base_v - top_v)) & (uu >= u0) & (uu <= u1)
    if sel.sum() < 20:
        raise RuleFailure("wrist", f"too few face pixels ({int(sel.sum())}) to learn skin colour")
    c = _chroma(image[vv[sel], uu[sel]])
    cov = np.cov(c.T) + 1e-5 * np.eye(2)
    return SkinModel(c.mean(axis=0), cov, int(sel.sum()))


def hand_ellipse(
    image: np.ndarray,
    mask: np.ndarray,
    elbow: np.ndarray,
    hand_tip: np.ndarray,
    skin: SkinModel,
    skin_threshold: float = 3.0,
    hand_start: float = 0.4,
    min_pixels: int = 15,
) -> Ellipse:
    """The ellipse of the skin-coloured pixels at the hand end of one forearm.

    Args:
        image: ``(H, W, 3)`` uint8 RGB.
        mask: ``(H, W)`` bool silhouette.
        elbow: ``(2,)`` elbow point, pixels.
        hand_tip: ``(2,)`` the hand's extremity on the outline, pixels.
        skin: from :func:`skin_model_from_face`.
        skin_threshold: largest Mahalanobis distance of a skin pixel.
        hand_start: only pixels more than this fraction of the way from elbow to tip count.
        min_pixels: fewest hand pixels for an ellipse.

    Raises:
        RuleFailure: ``"wrist"`` when too few skin pixels are found.
    """
    axis = np.asarray(hand_tip, dtype=np.float64) - elbow
    length = float(np.linalg.norm(axis))
    if length < 2.0:
        raise RuleFailure("wrist", "elbow and hand tip coincide")
    axis /= length
    vv, uu = np.nonzero(mask)
    rel = np.stack([uu, vv], axis=1) - elbow
    along = rel @ axis
    across = np.abs(rel @ np.array([-axis[1], axis[0]]))
    near = (along > hand_start * length) & (along < 1.2 * length) & (across < 0.6 * length)
    skin_px = near.copy()
    skin_px[near] = skin.distance(image[vv[near], uu[near]]) < skin_threshold
    if skin_px.sum() < min_pixels:
        raise RuleFailure("wrist", f"only {int(skin_px.sum())} skin-coloured pixels at the hand")
    blob = np.zeros(mask.shape, dtype=np.uint8)
    blob[vv[skin_px], uu[skin_px]] = 1
    n, labels, stats, _ = cv2.connectedComponentsWithStats(blob, connectivity=8)
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    bv, bu = np.nonzero(labels == biggest)
    if len(bu) < min_pixels:
        raise RuleFailure("wrist", f"the largest skin region at the hand has {len(bu)} pixels")
    pts = np.stack([bu, bv], axis=1).astype(np.float64)
    # Pixel squares add 1/12 to the variance of a continuous region.
    cov = np.cov(pts.T) + np.eye(2) / 12.0
    return Ellipse(pts.mean(axis=0), cov, len(pts))


def find_wrists(
    image: np.ndarray,
    mask: np.ndarray,
    labelling: Labelling,
    skin_threshold: float = 3.0,
    hand_start: float = 0.4,
    face_band: float = 0.45,
) -> dict[str, Ellipse]:
    """Add ``l_wrist`` and ``r_wrist`` to a successful labelling.

    The wrist is where the line from the elbow to the hand ellipse's centre enters the ellipse.

    Args:
        image: ``(H, W, 3)`` uint8 RGB.
        mask: ``(H, W)`` bool silhouette.
        labelling: a labelling with ``status == "ok"`` (modified in place).
        skin_threshold, hand_start, face_band: see :func:`hand_ellipse` and
            :func:`skin_model_from_face`.

    Returns:
        ``{"l_hand": Ellipse, "r_hand": Ellipse}``.

    Raises:
        RuleFailure: ``"wrist"`` when the skin colour or a hand is not found.
    """
    skin = skin_model_from_face(image, mask, labelling, face_band)
    out = {}
    for s in "lr":
        elbow = labelling.raw_joints[f"{s}_elbow"]
        ellipse = hand_ellipse(
            image, mask, elbow, labelling.landmarks[f"{s}_hand"], skin, skin_threshold, hand_start
        )
        out[f"{s}_hand"] = ellipse
        wrist = ellipse.boundary_towards(elbow)
        labelling.raw_joints[f"{s}_wrist"] = wrist
        labelling.joints[f"{s}_wrist"] = wrist.copy()
        labelling.anchors[f"{s}_wrist"] = wrist[None].copy()
    return out
