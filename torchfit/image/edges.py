"""Mixed pixels on a silhouette's outline: keep those that are mostly person.

Conventions: images ``(B, 3, H, W)`` RGB in ``[0, 1]``; masks ``(B, 1, H, W)`` bool.

A pixel that the silhouette's edge crosses records a mixture of the person's colour ``P`` and
the background's ``B``: ``I = a P + (1 - a) B`` with ``a`` the share of the pixel the person
covers. Lens blur, demosaicing and JPEG compression spread that mixture over a pixel or two
more. The colour test calls such a pixel person as soon as it differs from the background by
more than the noise, i.e. for a small ``a`` already, and the closing of the clean-up rounds
the outline outward: a silhouette comes out about a pixel fatter all around than the person's
true outline (the pixels at least half covered).

:func:`refine_edges` splits each outline pixel into its two sources. Within ``width`` pixels of
the outside, ``P`` is the mean colour of the silhouette's interior (the mask eroded by a
``(2 width + 1)`` square) over a ``(2 width + 3)`` square window around the pixel and ``B``
the background model's mean; the pixel's colour is fitted as ``I = s P + t B`` by least
squares. ``s`` is free (the person's outline is often shaded darker than its interior: a
surface turning away from the light), so only the background's share ``t`` measures the
coverage, ``1 - a``; a pixel with ``t > 1/2`` is background. Where ``B`` lies within
``separation`` standard deviations of the background's noise of the line through ``P`` (the
background is a shade of the person's colour: white clothing before a grey wall) the split is
not defined and the pixel stays as it is; so it does where no interior pixel lies in its window
(a thin limb, all outline). For one person the largest region is kept afterwards, so that the
outline never splits into fragments.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from torchfit.errors import SegmentationError
from torchfit.image.background import BackgroundModel
from torchfit.image.morphology import largest_component

__all__ = ["refine_edges"]

# the quantisation noise of 8-bit images, added to the model's variance
_NOISE_FLOOR = (1.0 / 255.0) ** 2


def refine_edges(
    images: torch.Tensor,
    background: BackgroundModel,
    masks: torch.Tensor,
    width: int = 2,
    separation: float = 6.0,
    largest_region: bool = True,
) -> torch.Tensor:
    """Drop the outline pixels that are more background than person (module docstring).

    Args:
        images: ``(B, 3, H, W)`` RGB in ``[0, 1]`` (photometrically matched, as tested).
        background: with ``rgb_mean`` (and ``rgb_var``), batch 1 or ``B``.
        masks: ``(B, 1, H, W)`` bool cleaned silhouettes.
        width: how far in from the outside (pixels) a pixel may be dropped; 0 returns
            ``masks``.
        separation: least distance of the background's colour from the person's colour line,
            in standard deviations of the background's noise, for the split to be made.
        largest_region: keep only the largest region afterwards (the masks hold one person);
            ``False`` only drops the pixels.

    Returns:
        ``(B, 1, H, W)`` bool, ``masks`` without the outline pixels that are mostly
        background (one region per image with ``largest_region``), on the masks' device.

    Raises:
        SegmentationError: the model has no ``rgb_mean``.
        ValueError: a negative ``width`` or ``separation``.
    """
    if width < 0 or separation < 0:
        raise ValueError(f"width and separation must be >= 0, got {width}, {separation}")
    if width == 0:
        return masks
    if background.rgb_mean is None:
        raise SegmentationError("background: refining the outline needs rgb_mean")
    out = masks.cpu().clone()
    kernel = np.ones((2 * width + 1, 2 * width + 1), np.uint8)
    win = (2 * width + 3, 2 * width + 3)
    pad = width + win[0]
    for b in range(masks.shape[0]):
        m = out[b, 0].numpy().view(np.uint8)
        x, y, w, h = cv2.boundingRect(m)
        if w == 0:
            continue
        y0, y1 = max(y - pad, 0), min(y + h + pad, m.shape[0])
        x0, x1 = max(x - pad, 0), min(x + w + pad, m.shape[1])
        mask = np.ascontiguousarray(m[y0:y1, x0:x1])
        inner = cv2.erode(mask, kernel, borderType=cv2.BORDER_REPLICATE)
        j = b if background.rgb_mean.shape[0] > 1 else 0
        img = images[b, :, y0:y1, x0:x1].float().cpu().numpy()
        bg = background.rgb_mean[j, :, y0:y1, x0:x1].float().cpu().numpy()
        rim = (mask > 0) & (inner == 0)
        ys, xs = np.nonzero(rim)
        if ys.size == 0:
            continue
        var = np.float32(_NOISE_FLOOR)
        if background.rgb_var is not None:
            var = var + background.rgb_var[j, 0, y0:y1, x0:x1].float().cpu().numpy()[ys, xs]
        weight = inner.astype(np.float32)
        count = cv2.boxFilter(weight, -1, win, normalize=False, borderType=cv2.BORDER_CONSTANT)
        n = count[ys, xs]
        scale = 1.0 / np.maximum(n, 1e-6)
        pp, pb, bb, pi, bi = (np.zeros(ys.size, np.float32) for _ in range(5))
        for c in range(3):  # the box sums densely (one SIMD pass), the rest on the rim only
            total = cv2.boxFilter(
                img[c] * weight, -1, win, normalize=False, borderType=cv2.BORDER_CONSTANT
            )
            p_c, b_c, i_c = total[ys, xs] * scale, bg[c][ys, xs], img[c][ys, xs]
            pp += p_c * p_c
            pb += p_c * b_c
            bb += b_c * b_c
            pi += p_c * i_c
            bi += b_c * i_c
        # I = s P + t B by least squares; the background's share t = (|P|^2 <B, I> - <P, B>
        # <P, I>) / det, det = |P|^2 |B_perp|^2 with B_perp the part of B off P's colour line
        det = pp * bb - pb * pb
        share = pp * bi - pb * pi
        lost = (n > 0.5) & (det >= separation**2 * var * pp) & (share > 0.5 * det)
        drop = np.zeros(mask.shape, dtype=bool)
        drop[ys[lost], xs[lost]] = True
        if drop.any():
            mask[drop] = 0
            kept = largest_component(mask) if largest_region else mask > 0
            out[b, 0, y0:y1, x0:x1] = torch.from_numpy(kept)
    return out.to(masks.device)
