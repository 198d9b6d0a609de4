"""Explicit cast-shadow test, restricted to the lowest band of the silhouette and bridged.

Conventions: images ``(B, 3, H, W)`` RGB in ``[0, 1]``; masks ``(B, 1, H, W)`` bool.

The first paper notes that shadow handling "could be improved by a similarity measure like in
[4]" (its reference [4]); :func:`shadow_mask` is such a measure, in the spirit of
brightness/chromaticity-distortion shadow detectors. With ``B`` the background's mean RGB and
``I`` the pixel's RGB (both 0–1, as stored, i.e. gamma encoded; a uniform darkening stays
uniform under the power law), the brightness ratio is ``alpha = <I, B> / |B|^2`` and the colour
change is the angle between ``I`` and ``B``. A pixel is shadow-like when
``ratio[0] <= alpha <= ratio[1]`` and the angle is at most ``max_angle`` radians: darker, same
colour direction.

Colour alone cannot tell a shadow from grey clothing in front of a lighter grey wall (both are
"darker, same direction"), so :func:`lower_band` limits the test to the lowest fraction of the
foreground's vertical extent, where a standing person's floor shadow lies. A shin in trousers
of the floor's colour passes the test as well and cuts the feet off the silhouette;
:func:`bridged` finds the shadow-like pixels that have person (non-shadow foreground) both
above and below them in their image column, as a shin between the knee and a shoe has and a
shadow cast on the floor beside, behind or in front of the feet has not.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchfit.errors import SegmentationError
from torchfit.image.background import BackgroundModel, _check_images
from torchfit.image.morphology import binary_opening, largest_component

__all__ = ["shadow_mask", "lower_band", "bridged"]


def shadow_mask(
    model: BackgroundModel,
    images: torch.Tensor,
    ratio: tuple[float, float] = (0.5, 0.95),
    max_angle: float = 0.05,
) -> torch.Tensor:
    """Pixels that look like a cast shadow on the background (see the module docstring).

    Args:
        model: with ``rgb_mean`` (from :func:`~torchfit.image.background.fit_background`),
            batch 1 or ``B``.
        images: ``(B, 3, H, W)`` RGB in ``[0, 1]``, the size of the model.
        ratio: ``(low, high)`` bounds of the brightness ratio ``<I, B> / |B|^2``.
        max_angle: largest angle (radians) between the pixel's and the background's RGB.

    Returns:
        ``(B, 1, H, W)`` bool, True where the pixel is a darker copy of the background.

    Raises:
        ShapeError: for a wrongly shaped ``images``.
        SegmentationError: if the model has no ``rgb_mean`` or the sizes differ.
    """
    _check_images("images", images, 1)
    if model.rgb_mean is None:
        raise SegmentationError("model: the shadow test needs rgb_mean (use fit_background)")
    if images.shape[-2:] != model.rgb_mean.shape[-2:]:
        raise SegmentationError(
            f"images: expected size {tuple(model.rgb_mean.shape[-2:])} (HxW) of the background "
            f"model, got {tuple(images.shape[-2:])}"
        )
    low, high = ratio
    if not 0.0 < low <= high:
        raise ValueError(f"ratio must satisfy 0 < low <= high, got {ratio}")
    bg = model.rgb_mean.to(images.dtype)
    dot = (images * bg).sum(1, keepdim=True)
    bb = bg.square().sum(1, keepdim=True).clamp_min(1e-6)
    ii = images.square().sum(1, keepdim=True).clamp_min(1e-6)
    alpha = dot / bb
    cos = (dot / (bb * ii).sqrt()).clamp(-1.0, 1.0)
    return (alpha >= low) & (alpha <= high) & (cos >= math.cos(max_angle))


def lower_band(masks: torch.Tensor, fraction: float, open_kernel: int) -> torch.Tensor:
    """The rows in the lowest ``fraction`` of each mask's vertical extent.

    The extent is measured after an opening by ``open_kernel``, so that speckles do not count.

    Args:
        masks: ``(B, 1, H, W)`` bool foreground.
        fraction: in ``(0, 1]``, the share of the extent (from its bottom row) to keep.
        open_kernel: side of the square opening element (odd); ``<= 1`` skips the opening.

    Returns:
        ``(B, 1, H, W)`` bool, ``True`` on every pixel of the band's rows.
    """
    opened = binary_opening(masks, open_kernel) if open_kernel > 1 else masks
    rows = opened.any(3, keepdim=True)  # (B, 1, H, 1)
    h = masks.shape[2]
    idx = torch.arange(h, device=masks.device).view(1, 1, h, 1)
    top = torch.where(rows, idx, h).amin(2, keepdim=True)
    bottom = torch.where(rows, idx, -1).amax(2, keepdim=True)
    start = bottom - fraction * (bottom - top).clamp_min(0)
    return (idx >= start).expand_as(masks)


def bridged(person: torch.Tensor, open_kernel: int) -> torch.Tensor:
    """Pixels between the main person region above and a cut-off person region below.

    ``person`` is opened by ``open_kernel`` first, so that speckles do not count. Feet still
    joined to the body do not bridge anything: a shadow between a calf and its own foot (beside
    the ankle) stays shadow.

    Args:
        person: ``(B, 1, H, W)`` bool, the foreground without the shadow-like pixels.
        open_kernel: side of the square opening element (odd); ``<= 1`` skips the opening.

    Returns:
        ``(B, 1, H, W)`` bool, ``True`` outside ``person`` where the main (largest) region lies
        somewhere above in the pixel's column and another region somewhere below.
    """
    solid = binary_opening(person, open_kernel) if open_kernel > 1 else person
    host = solid.cpu().numpy()
    main = np.stack([largest_component(m) for m in host.reshape(-1, *host.shape[-2:])])
    main = torch.from_numpy(main.reshape(host.shape).astype(np.uint8)).to(person.device)
    cut_off = solid.to(torch.uint8) & (1 - main)
    above = torch.cummax(main, dim=2).values.bool()
    below = torch.cummax(cut_off.flip(2), dim=2).values.flip(2).bool()
    return above & below & ~person
