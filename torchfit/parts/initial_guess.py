"""The automatic initial guess from one camera (interface; the fit integrates it).

From posture 5 (cactus) the rules give 2-D joints; from posture 1 (stand) the silhouette gives
the image extents of the body. The lead turns these into a root position, an overall scale and
arm segment scales. Pixels ``(u, v)``, ``v`` down; ``l_*`` joints on the image right.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from torchfit.image.morphology import fill_holes
from torchfit.parts.decompose import decompose_cactus
from torchfit.parts.errors import PartsError
from torchfit.parts.options import PartsOptions
from torchfit.parts.rules import Labelling

__all__ = ["PostureExtents", "InitialGuess2D", "posture_extents", "initial_guess_2d"]


@dataclass
class PostureExtents:
    """Image extents of a standing silhouette (posture 1).

    Attributes:
        head_top: ``(2,)`` ``(u, v)`` the highest silhouette pixel (middle of its row's run).
        lowest_foot: ``(2,)`` ``(u, v)`` the lowest silhouette pixel (middle of its row's run).
        width_px: widest horizontal extent of the silhouette, pixels (arms included).
        height_px: ``lowest_foot v - head_top v``, pixels.
    """

    head_top: np.ndarray
    lowest_foot: np.ndarray
    width_px: float
    height_px: float


@dataclass
class InitialGuess2D:
    """What the silhouettes of one camera say about a subject before fitting.

    Attributes:
        status: ``"ok"`` or ``"failed"`` (then ``joints_pose5`` is empty and/or
            ``extents_pose1`` is None).
        failed_rule: ``"pose1"`` (empty posture-1 silhouette) or the posture-5 rule that
            failed (:data:`torchfit.parts.RULE_NAMES`, ``"contour"``); None when ok.
        message: the reason ("" when ok).
        joints_pose5: joint name -> ``(2,)`` ``(u, v)`` pixels in the posture-5 image:
            ``back``, ``neck``, ``l_shoulder``, ``r_shoulder``, ``l_elbow``, ``r_elbow`` and,
            when the image was given and the hands were found, ``l_wrist``, ``r_wrist``. These
            are joint-centre estimates (the :class:`~torchfit.parts.JointOffsets` corrections
            applied); ``back`` is the pelvis (midpoint of the hip joint centres).
        extents_pose1: the posture-1 extents, None when that silhouette is empty.
        labelling: the full posture-5 labelling (cuts, spline, extrema) for overlays.
    """

    status: str
    failed_rule: str | None = None
    message: str = ""
    joints_pose5: dict[str, np.ndarray] = field(default_factory=dict)
    extents_pose1: PostureExtents | None = None
    labelling: Labelling | None = None


def _mask(x: np.ndarray | torch.Tensor, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    x = np.asarray(x)
    while x.ndim > 2 and x.shape[0] == 1:
        x = x[0]
    if x.ndim != 2:
        raise PartsError(f"{name}: expected shape (H, W) (or (1, 1, H, W)), got {x.shape}")
    return x != 0


def posture_extents(mask: np.ndarray | torch.Tensor) -> PostureExtents | None:
    """Extents of a silhouette: top and bottom pixels and width (None for an empty mask).

    Args:
        mask: ``(H, W)`` silhouette.
    """
    m = fill_holes(_mask(mask, "mask"))
    rows = np.nonzero(m.any(axis=1))[0]
    if len(rows) == 0:
        return None
    top, bottom = rows[0], rows[-1]
    cols = np.nonzero(m.any(axis=0))[0]
    return PostureExtents(
        head_top=np.array([float(np.nonzero(m[top])[0].mean()), float(top)]),
        lowest_foot=np.array([float(np.nonzero(m[bottom])[0].mean()), float(bottom)]),
        width_px=float(cols[-1] - cols[0] + 1),
        height_px=float(bottom - top),
    )


def initial_guess_2d(
    mask_pose5: np.ndarray | torch.Tensor,
    mask_pose1: np.ndarray | torch.Tensor,
    image_pose5: np.ndarray | None = None,
    config: PartsOptions | None = None,
) -> InitialGuess2D:
    """2-D joints of posture 5 and extents of posture 1, from one camera.

    Args:
        mask_pose5: ``(H, W)`` posture-5 silhouette (holes may stay open, see
            :func:`~torchfit.parts.decompose_cactus`).
        mask_pose1: ``(H, W)`` posture-1 silhouette.
        image_pose5: ``(H, W, 3)`` uint8 RGB posture-5 image, for the wrists (optional).
        config: decomposition options.

    Returns:
        An :class:`InitialGuess2D`; never raises for content (a failed rule is a status).

    Raises:
        PartsError: a mask or the image has the wrong shape.
    """
    m5 = _mask(mask_pose5, "mask_pose5")
    extents = posture_extents(mask_pose1)
    labelling = decompose_cactus(m5, image_pose5, config)
    out = InitialGuess2D(status="ok", extents_pose1=extents, labelling=labelling)
    if not labelling.ok:
        out.status, out.failed_rule = "failed", labelling.failed_rule
        out.message = f"pose5: {labelling.message}"
    else:
        out.joints_pose5 = {k: v.copy() for k, v in labelling.joints.items()}
    if extents is None:
        out.status, out.failed_rule = "failed", out.failed_rule or "pose1"
        out.message = (out.message + "; " if out.message else "") + "pose1: empty silhouette"
    return out
