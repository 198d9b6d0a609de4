"""Photometric compensation: undo a frame's exposure and white-balance change before the test.

Conventions: images ``(B, 3, H, W)`` RGB in ``[0, 1]`` as stored (gamma encoded, 8-bit
quantised); the background is the model's mean RGB ``(B_m, 3, H, W)``, ``B_m`` 1 or ``B``.

**Model.** A change of exposure or of the white balance between the background frames and a
posture frame multiplies each channel by a gain ``g_c``. In linear light that is exact; through
a power-law response ``x -> x^(1/gamma)`` a gain stays a gain (``(k x)^(1/gamma) =
k^(1/gamma) x^(1/gamma)``), so the stored values obey ``I_c = g_c B_c`` on the background too.
No offset is estimated: an offset only appears with a change of black level, which cameras
hold, and a gain alone is better conditioned on scenes with a narrow range of brightness.

**Estimate**, per frame on its own (a slow drift over a capture is followed frame by frame):
on a regular subsample of the pixels whose background and image values are all in
``[dark, bright]`` (neither lost in the quantisation noise near black nor clipped near white),
take ``r_c = log I_c - log B_c``. The background is the largest group of pixels sharing one
``r``; the person and cast shadows have other ratios. The start is the peak of each channel's
histogram of ``r_c`` (lightly smoothed); then, a few times, the pixels within ``window`` of
the current estimate in *all three* channels are the inliers and the estimate moves to their
per-channel median (a median mean-shift, which converges on the mode). Where fewer than
``min_inliers`` of the usable pixels agree, or a gain leaves ``[1 / max_gain, max_gain]``, or
too few pixels are usable (an all-black or all-white frame), the frame is left as it is (gain
1): a wrong correction would do more harm than none.

**Only what matters** (:func:`match_background`): the gains are undone only where that takes at
least ``min_effect`` of the pixels from "person" to "background" in the colour test. A drift
the background frames showed themselves (a temporal-median background over a capture whose
exposure wanders by a few per cent) is already in the model's covariance; undoing it changes
nothing the test sees but moves a few marginal pixels, so a scene without a real change is
segmented as without compensation.

**Undo.** ``I_c / g_c``, clamped to ``[0, 1]``. An 8-bit value at the top of the range only
says that the true value was at least that; where the image is clipped in a channel and
``I_c / g_c`` is darker than the background, the compensated value is the background's, the
one value consistent with both (a brighter frame clips a light wall that the background frames
still resolved; without this the clipped wall would differ from the background by the gain).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchfit.errors import SegmentationError
from torchfit.image.background import BackgroundModel, _check_images, _distance_kernel

__all__ = [
    "PhotometricResult",
    "estimate_gains",
    "compensate",
    "match_background",
    "sample_stride",
]

# 8-bit levels outside which a value says little about a gain: quantisation noise near black,
# clipping near white
_DARK = 12.0 / 255.0
_BRIGHT = 250.0 / 255.0
# log-ratio histogram: bins of 0.005 (half a per cent) over gains 1/2 .. 2
_BIN = 0.005
_SPAN = 0.7
# an 8-bit 255: the true value may have been anything above
_CLIPPED = 254.5 / 255.0


@dataclass
class PhotometricResult:
    """The output of :func:`estimate_gains`.

    Attributes:
        gains: ``(B, 3)`` per-channel gains, image = gain * background (1 where not estimated).
        inliers: ``(B,)`` fraction of the usable sampled pixels that agree with the gains.
        estimated: ``(B,)`` bool, ``False`` where no gains could be estimated.
        applied: ``(B,)`` bool, where :func:`match_background` undid the gains.
        effect: ``(B,)`` net share of the sampled pixels that the compensation took from
            person to background in the colour test (:func:`match_background`; 0 otherwise).
    """

    gains: torch.Tensor
    inliers: torch.Tensor
    estimated: torch.Tensor
    applied: torch.Tensor
    effect: torch.Tensor

    @property
    def undone(self) -> torch.Tensor:
        """``(B, 3)`` the gains actually undone (1 where none was applied)."""
        return torch.where(self.applied.view(-1, 1), self.gains.cpu(), 1.0)


def sample_stride(images: torch.Tensor, samples: int = 6_000) -> int:
    """The pixel step (in each direction) that leaves about ``samples`` pixels of an image."""
    h, w = images.shape[-2:]
    return max(1, int(math.sqrt(h * w / samples)))


def _mode(values: torch.Tensor) -> float:
    """Peak of a lightly smoothed histogram of log-ratios ``(N,)`` in ``[-_SPAN, _SPAN]``."""
    bins = int(round(2 * _SPAN / _BIN))
    hist = torch.histc(values, bins=bins, min=-_SPAN, max=_SPAN)
    hist = torch.nn.functional.avg_pool1d(hist.view(1, 1, -1), 5, 1, 2).view(-1)
    return -_SPAN + (int(hist.argmax()) + 0.5) * _BIN


def estimate_gains(
    images: torch.Tensor,
    background: torch.Tensor,
    stride: int | None = None,
    window: float = 0.04,
    min_inliers: float = 0.2,
    max_gain: float = 1.6,
    iterations: int = 5,
) -> PhotometricResult:
    """Per-channel gains from the background to each image (see the module docstring).

    Args:
        images: ``(B, 3, H, W)`` RGB in ``[0, 1]``.
        background: ``(B_m, 3, H, W)`` mean RGB of the background frames in ``[0, 1]``,
            ``B_m`` 1 or ``B``.
        stride: sample every ``stride``-th pixel in each direction; None: about 6 000
            samples (every 8th pixel at 720x576).
        window: half-width, in log-ratio (about a fraction), of the inlier window.
        min_inliers: least fraction of the usable samples that must agree with the gains.
        max_gain: largest gain (and ``1 / max_gain`` the smallest) accepted.
        iterations: median mean-shift steps.

    Returns:
        :class:`PhotometricResult`.

    Raises:
        ShapeError: wrongly shaped images or background.
        SegmentationError: sizes or batches that do not match.
    """
    _check_images("images", images, 1)
    _check_images("background", background, 1)
    if images.shape[-2:] != background.shape[-2:]:
        raise SegmentationError(
            f"images: expected size {tuple(background.shape[-2:])} (HxW) of the background, "
            f"got {tuple(images.shape[-2:])}"
        )
    b = images.shape[0]
    if background.shape[0] not in (1, b):
        raise SegmentationError(
            f"images: batch {b} does not match the background's batch {background.shape[0]}"
        )
    stride = stride or sample_stride(images)
    img = images[..., ::stride, ::stride].float().flatten(2)  # (B, 3, N)
    bg = background[..., ::stride, ::stride].float().flatten(2).expand(b, -1, -1)
    usable = ((img > _DARK) & (img < _BRIGHT) & (bg > _DARK) & (bg < _BRIGHT)).all(1)  # (B, N)
    # a few thousand samples per image: the robust fit runs on the CPU
    ratio = (img.clamp_min(_DARK).log() - bg.clamp_min(_DARK).log()).cpu()
    usable = usable.cpu()
    gains = torch.ones(b, 3)
    inliers = torch.zeros(b)
    estimated = torch.zeros(b, dtype=torch.bool)
    limit = abs(torch.log(torch.tensor(max_gain)).item())
    for i in range(b):
        r = ratio[i][:, usable[i]]  # (3, n)
        n = r.shape[1]
        if n < 100:
            continue
        est = torch.tensor([_mode(r[c]) for c in range(3)]).view(3, 1)
        agree = torch.zeros(n, dtype=torch.bool)
        for _ in range(iterations):
            agree = ((r - est).abs() <= window).all(0)
            if int(agree.sum()) < 10:
                break
            est = r[:, agree].median(1).values.view(3, 1)
        agree = ((r - est).abs() <= window).all(0)
        inliers[i] = agree.float().mean()
        if inliers[i] >= min_inliers and bool((est.abs() <= limit).all()):
            gains[i] = est.view(3).exp()
            estimated[i] = True
    return PhotometricResult(
        gains.to(images.device),
        inliers,
        estimated,
        torch.zeros(b, dtype=torch.bool),
        torch.zeros(b),
    )


def compensate(images: torch.Tensor, background: torch.Tensor, gains: torch.Tensor) -> torch.Tensor:
    """Divide each image by its per-channel gains, minding 8-bit clipping.

    Args:
        images: ``(B, 3, H, W)`` RGB in ``[0, 1]``.
        background: ``(B_m, 3, H, W)`` mean RGB of the background frames, ``B_m`` 1 or ``B``.
        gains: ``(B, 3)`` from :func:`estimate_gains`.

    Returns:
        ``(B, 3, H, W)`` the images as the background's exposure and white balance would have
        recorded them, same dtype.
    """
    g = gains.to(images.dtype).view(-1, 3, 1, 1)
    out = (images / g).clamp_(0.0, 1.0)
    # clipped pixels: max(I / g, B); elsewhere max(I / g, 0) = I / g
    floor = (images >= _CLIPPED).to(images.dtype).mul_(background.to(images.dtype))
    return torch.maximum(out, floor, out=out)


def match_background(
    images: torch.Tensor,
    model: BackgroundModel,
    threshold: float = 4.0,
    min_effect: float = 0.02,
    stride: int | None = None,
) -> tuple[torch.Tensor, PhotometricResult]:
    """Estimate each image's gains against the background model and undo those that matter.

    A compensation is applied only where it changes the colour test's answer on at least
    ``min_effect`` of the (sampled) pixels, from person to background: a gain that the test
    does not notice (a drift that the background frames themselves showed, and that the
    model's covariance already holds) is left alone, so that a scene without a change of
    exposure or white balance is segmented exactly as without compensation.

    Args:
        images: ``(B, 3, H, W)`` RGB in ``[0, 1]``.
        model: from :func:`~torchfit.image.background.fit_background` (with ``rgb_mean``).
        threshold: the colour test's Mahalanobis threshold.
        min_effect: least net share of the sampled pixels that the compensation must take from
            above to below ``threshold``. The default, 2 % of the image, is about half the
            area of a person framed whole (3-6 % in the demo); a global change of exposure
            that matters turns much of the background into "person" (demo posture images 3 %
            brighter: 60 % of the image on average, ``benchmarks/eval_photometric.py``).
        stride: sample every ``stride``-th pixel in each direction (estimate and effect);
            None: about 6 000 samples.

    Returns:
        The ``(B, 3, H, W)`` images, compensated where applied, and the
        :class:`PhotometricResult`.

    Raises:
        SegmentationError: the model has no ``rgb_mean``, or the sizes differ.
    """
    if model.rgb_mean is None:
        raise SegmentationError(
            "model: photometric compensation needs rgb_mean (use fit_background), "
            "or set segmentation.photometric: false"
        )
    stride = stride or sample_stride(images)
    result = estimate_gains(images, model.rgb_mean, stride=stride)
    if not bool(result.estimated.any()):
        return images, result
    sub = (slice(None), slice(None), slice(None, None, stride), slice(None, None, stride))

    def flagged(x: torch.Tensor) -> torch.Tensor:
        d = _distance_kernel(
            x, model.mean[sub], model.precision[sub], model.color_space, model.gamma
        )
        return (d > threshold).flatten(1).float().mean(1).cpu()

    # the effect on the samples first: a frame without a change costs no full-size pass
    sampled = images[sub]
    undone = compensate(sampled, model.rgb_mean[sub], result.gains)
    result.effect = flagged(sampled) - flagged(undone)
    result.applied = result.estimated & (result.effect >= min_effect)
    if not bool(result.applied.any()):
        return images, result
    if bool(result.applied.all()):
        return compensate(images, model.rgb_mean, result.gains), result
    idx = result.applied.nonzero()[:, 0].to(images.device)
    bg = model.rgb_mean if model.rgb_mean.shape[0] == 1 else model.rgb_mean[idx]
    out = images.clone()
    out[idx] = compensate(images[idx], bg, result.gains[idx])
    return out, result
