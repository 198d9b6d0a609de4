"""Explicit cast-shadow test: attenuation, chromaticity and texture against the background.

Conventions: images ``(B, 3, H, W)`` RGB in ``[0, 1]``; masks ``(B, 1, H, W)`` bool.

The first paper notes that shadow handling "could be improved by a similarity measure like in
[4]" (its reference [4]); :func:`shadow_mask` is such a measure. A cast shadow attenuates the
light reaching a surface: the pixel becomes a darker copy of the background, with the same
chromaticity and the same texture. With ``B`` the background's mean RGB and ``I`` the pixel's
RGB (both 0–1, as stored, i.e. gamma encoded; a uniform darkening stays uniform under the
power law) and ``sigma^2`` the background's per-pixel noise variance
(:attr:`~torchfit.image.background.BackgroundModel.rgb_var`), a pixel is shadow-like when

1. **attenuation**: ``ratio[0] <= alpha <= ratio[1]`` with ``alpha = <I, B> / |B|^2``;
2. **chromaticity**: the colour distortion ``|I - alpha B|`` (the distance from the line
   through the background colour) is at most ``max_angle * alpha |B| + noise * sqrt(2) sigma``:
   an angle for the tint of the ambient light, plus the noise a pixel shows on its own (the
   perpendicular part of an isotropic 3-D noise has two degrees of freedom), so a noisy pixel
   is allowed more distortion than a steady one;
3. **texture**: over a ``window`` x ``window`` box of *candidates* (pixels that pass 1 and 2
   and, where ``foreground`` is given, that the colour test took for the person), compare the
   frame's luma gradients ``g_I`` with the background's ``g_B``. Where the background is
   textured, its attenuated gradient energy ``alpha^2 mean(|g_B|^2)`` at least ``min_texture``
   times the gradient noise ``sigma^2``, the regression slope
   ``beta = sum(w g_I . g_B) / sum(w |g_B|^2)`` must be at least ``texture * alpha``: a shadow
   keeps the background's edges, scaled by ``alpha`` (``beta ~ alpha``); a person in front of
   a textured background does not (``beta ~ 0``, whatever the person's own texture or
   colour). The weights ``w = 1 / (1 + |g_I - alpha g_B|^2 / (4 (alpha^2 |g_B|^2 +
   sigma^2)))`` are one step of a robust (Cauchy) regression, so that the shadow's own border
   (a step of ``alpha``) hardly counts. Where the background is flat the texture cannot
   confirm a shadow; there the frame must be flat too, up to a smooth change of attenuation
   (a penumbra): the spread (variance over the box) of ``g_I - alpha g_B`` is at most
   ``max_residual * sigma^2``. A person's folds, shading and texture spread more.

A darker part of the person (a self-shadow on the body) fails test 2 or 3: it is a darker copy
of the person, not of the background. What no local test can separate is smooth clothing that
is a darker copy of a flat background (a plain grey shirt in front of a lighter, untextured grey
wall): it passes all three tests.

Where background and frame are both flat, ``flat_allowed`` can restrict the shadow decision
to a region (``SegmentationOptions.shadow_flat_band``: the lowest part of the foreground, where
the floor shadow lies). Two position heuristics from the floor-shadow test remain as options
(off by default):
:func:`lower_band` limits the test to the lowest fraction of the foreground's vertical extent,
and :func:`bridged` finds the shadow-like pixels that have person (non-shadow foreground) both
above and below them in their image column, as a shin between the knee and a shoe has and a
shadow cast on the floor beside, behind or in front of the feet has not.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812

from torchfit.errors import SegmentationError
from torchfit.image.background import BackgroundModel, _check_images, _opencv_eligible
from torchfit.image.morphology import binary_opening, largest_component

__all__ = ["shadow_mask", "lower_band", "bridged"]

# noise variance used where a model has no rgb_var, and added to every pixel's: the
# quantisation floor of 8-bit images, (1 / 255)^2 (a step of one level)
_NOISE_FLOOR = (1.0 / 255.0) ** 2


def _luma_gradients(luma: torch.Tensor) -> torch.Tensor:
    """``(N, 1, H, W)`` -> ``(N, 2, H, W)`` central differences (x, y), replicate border."""
    padded = F.pad(luma, (1, 1, 1, 1), mode="replicate")
    gx = 0.5 * (padded[..., 1:-1, 2:] - padded[..., 1:-1, :-2])
    gy = 0.5 * (padded[..., 2:, 1:-1] - padded[..., :-2, 1:-1])
    return torch.cat([gx, gy], 1)


def _box_sums(x: torch.Tensor, window: int) -> torch.Tensor:
    """Sums of ``x (N, C, H, W)`` over ``window`` x ``window`` boxes centred on each pixel (zero
    outside the image). On the CPU in float32 OpenCV's box filter (one SIMD pass per plane);
    elsewhere running sums along each axis in turn (about four times faster on CPU than
    ``avg_pool2d`` with this window). The shadow test needs only ratios of sums."""
    if _opencv_eligible(x):
        src = x.contiguous()
        out = torch.empty_like(src)
        s, d = src.numpy(), out.numpy()
        for n in range(s.shape[0]):
            for c in range(s.shape[1]):
                cv2.boxFilter(
                    s[n, c],
                    -1,
                    (window, window),
                    dst=d[n, c],
                    normalize=False,
                    borderType=cv2.BORDER_CONSTANT,
                )
        return out
    r = window // 2
    c = F.pad(x, (r + 1, r)).cumsum(-1)
    x = c[..., window:] - c[..., :-window]
    c = F.pad(x, (0, 0, r + 1, r)).cumsum(-2)
    return c[..., window:, :] - c[..., :-window, :]


# the channels of the packed background terms (_background_terms)
_TERMS = {"bg": slice(0, 3), "sigma": slice(3, 4), "bb": slice(4, 5), "norm": slice(5, 6)}
_TERMS |= {"g_bg": slice(6, 8), "energy": slice(8, 9), "var": slice(9, 10)}


def _unpack(packed: torch.Tensor) -> dict[str, torch.Tensor]:
    return {k: packed[:, v] for k, v in _TERMS.items()}


def _background_terms(model: BackgroundModel, dtype: torch.dtype) -> torch.Tensor:
    """What the shadow test needs of the background alone, packed in one ``(B_m, 10, H, W)``
    tensor (channels in ``_TERMS``, read with :func:`_unpack`): the mean RGB ``bg``, the
    noise's standard deviation ``sigma`` and variance ``var`` (with the quantisation floor),
    ``|B|^2`` and ``|B|``, the luma gradients ``g_bg`` and their energy ``|g_B|^2``. Computed
    once per model and dtype (:meth:`BackgroundModel.cached`); one tensor, so that a crop of
    it is made contiguous in one copy."""

    def make(m: BackgroundModel) -> torch.Tensor:
        bg = m.rgb_mean.to(dtype)
        var = torch.full_like(bg[:, :1], _NOISE_FLOOR)
        if m.rgb_var is not None:
            var = m.rgb_var.to(dtype) + _NOISE_FLOOR
        bb = bg.square().sum(1, keepdim=True).clamp_min(1e-6)
        g_bg = _luma_gradients(bg.mean(1, keepdim=True))
        energy = g_bg.square().sum(1, keepdim=True)
        return torch.cat([bg, var.sqrt(), bb, bb.sqrt(), g_bg, energy, var], 1).contiguous()

    return model.cached(("shadow", dtype), make)


def _attenuation(
    images: torch.Tensor,
    terms: dict[str, torch.Tensor],
    low: float,
    high: float,
    max_angle: float,
    noise: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Tests 1 and 2 of the module docstring: ``alpha`` and the shadow-like pixels (bool)."""
    bg = terms["bg"]
    dot = images[:, 0:1] * bg[:, 0:1]
    dot.addcmul_(images[:, 1:2], bg[:, 1:2]).addcmul_(images[:, 2:3], bg[:, 2:3])
    ii = images[:, 0:1] * images[:, 0:1]
    ii.addcmul_(images[:, 1:2], images[:, 1:2]).addcmul_(images[:, 2:3], images[:, 2:3])
    alpha = dot / terms["bb"]
    # |I - alpha B|^2 = |I|^2 - <I, B>^2 / |B|^2 (the part of I off the background's colour
    # line), compared squared (the allowance is never negative)
    off2 = ii.sub_(dot.mul_(alpha))
    allowed = alpha.clamp_min(0.0).mul_(terms["norm"]).mul_(max_angle)
    allowed.add_(terms["sigma"], alpha=noise * math.sqrt(2.0))
    shadow = (alpha >= low) & (alpha <= high) & (off2 <= allowed.mul_(allowed))
    return alpha, shadow


def shadow_mask(
    model: BackgroundModel,
    images: torch.Tensor,
    ratio: tuple[float, float] = (0.3, 1.0),
    max_angle: float = 0.03,
    noise: float = 1.0,
    window: int = 7,
    texture: float = 0.5,
    min_texture: float = 0.5,
    max_residual: float = 10.0,
    foreground: torch.Tensor | None = None,
    flat_allowed: torch.Tensor | None = None,
    within: torch.Tensor | None = None,
) -> torch.Tensor:
    """Pixels that look like a cast shadow on the background (see the module docstring).

    Args:
        model: with ``rgb_mean`` (and ``rgb_var``; without it only the quantisation noise of
            8-bit images is assumed) from :func:`~torchfit.image.background.fit_background`,
            batch 1 or ``B``. Its background-side quantities (gradients, norms, noise) are
            computed on the first call and kept with it.
        images: ``(B, 3, H, W)`` RGB in ``[0, 1]``, the size of the model.
        ratio: ``(low, high)`` bounds of the brightness ratio ``<I, B> / |B|^2``.
        max_angle: colour distortion allowed beyond the noise, as an angle (radians) between
            the pixel's and the background's RGB.
        noise: colour distortion allowed for the noise, in standard deviations of the
            background's per-pixel noise.
        window: side (odd, pixels) of the box over which the textures are compared.
        texture: smallest slope of the frame's gradients on the background's, relative to
            ``alpha``, for a shadow on textured background, in ``[0, 1]``.
        min_texture: background gradient energy (attenuated by ``alpha``), in units of the
            gradient noise, above which the texture decides; ``inf`` turns the texture test
            off.
        max_residual: on flat background, the largest spread of the frame's gradients that
            attenuation does not explain, in units of the gradient noise.
        foreground: ``(B, 1, H, W)`` bool, the pixels the colour test took for the person,
            or None; with it the windows see only foreground candidates, only foreground
            pixels are decided (the rest is False), and every test runs on the box around
            each image's foreground alone.
        flat_allowed: ``(B, 1, H, W)`` bool, where a pixel on flat background may be called
            a shadow (e.g. :func:`lower_band`), or None for everywhere.
        within: ``(B, 1, H, W)`` bool, with ``foreground``: decide only the pixels of
            ``within`` (False elsewhere), or None for all. The segmentation passes the
            foreground after its opening: what the opening removes is background whatever
            the shadow test says, and the scattered noise pixels of the colour test then do
            not stretch the boxes the test runs on over the whole frame. The windows still
            see every candidate, so on ``within`` the result is the same.

    Returns:
        ``(B, 1, H, W)`` bool, True where the pixel is an attenuated copy of the background.

    Raises:
        ShapeError: for a wrongly shaped ``images``.
        SegmentationError: if the model has no ``rgb_mean`` or the sizes differ.
        ValueError: for bounds or a window out of range.
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
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 1, got {window}")
    if max_angle < 0 or noise < 0 or min_texture < 0:
        raise ValueError(
            f"max_angle, noise and min_texture must be >= 0, got {max_angle}, {noise}, "
            f"{min_texture}"
        )
    packed = _background_terms(model, images.dtype)
    tests = (low, high, max_angle, noise, window, texture, min_texture, max_residual)
    if foreground is not None:
        return _foreground_only(packed, images, foreground, flat_allowed, within, tests)
    terms = _unpack(packed)
    alpha, shadow = _attenuation(images, terms, low, high, max_angle, noise)
    if math.isinf(min_texture) or not bool(shadow.any()):
        return shadow
    return shadow & _texture_decides(
        images, terms, alpha, shadow, window, texture, min_texture, max_residual, flat_allowed
    )


def _box(mask: torch.Tensor, margin: int) -> tuple[int, int, int, int] | None:
    """``(y0, y1, x0, x1)``: the bounding box of ``mask (H, W)`` grown by ``margin`` and
    clipped to the image, or None for an empty mask."""
    h, w = mask.shape
    if mask.device.type == "cpu":  # one SIMD pass, several times faster than two any()s
        x, y, bw, bh = cv2.boundingRect(mask.contiguous().numpy().view(np.uint8))
        if bw == 0:
            return None
        y0, y1, x0, x1 = y, y + bh, x, x + bw
    else:
        rows = mask.any(1).nonzero()
        if rows.numel() == 0:
            return None
        cols = mask.any(0).nonzero()
        y0, y1 = int(rows[0, 0]), int(rows[-1, 0]) + 1
        x0, x1 = int(cols[0, 0]), int(cols[-1, 0]) + 1
    return max(y0 - margin, 0), min(y1 + margin, h), max(x0 - margin, 0), min(x1 + margin, w)


def _crop(t: torch.Tensor | None, b: int, box: tuple[int, int, int, int]):
    if t is None:
        return None
    i = b if t.shape[0] > 1 else 0
    return t[i : i + 1, :, box[0] : box[1], box[2] : box[3]]


def _foreground_only(
    packed: torch.Tensor,
    images: torch.Tensor,
    foreground: torch.Tensor,
    flat_allowed: torch.Tensor | None,
    within: torch.Tensor | None,
    tests: tuple,
) -> torch.Tensor:
    """The shadow test image by image: tests 1 and 2 on the box around the pixels to decide
    (``within``, or the foreground) grown by a margin, test 3 on the box around the
    candidates to decide; False elsewhere. The same result on the decided pixels as on the
    whole frame: a pixel's windows and gradients reach ``window // 2 + 1`` pixels, and each
    box keeps that margin. Small boxes one at a time stay in the cache, which the whole
    batch at once does not."""
    low, high, max_angle, noise, window, texture, min_texture, max_residual = tests
    out = torch.zeros_like(foreground)
    margin = window // 2 + 1
    select = foreground if within is None else within & foreground
    for b in range(images.shape[0]):
        box = _box(select[b, 0], margin)
        if box is None:
            continue
        crop_terms = _unpack(_crop(packed, b, box))
        img = _crop(images, b, box)
        alpha, shadow = _attenuation(img, crop_terms, low, high, max_angle, noise)
        cand = shadow & _crop(foreground, b, box)
        target = cand & _crop(select, b, box)
        inner = _box(target[0, 0], margin)
        if inner is None:
            continue
        region = out[b : b + 1, :, box[0] : box[1], box[2] : box[3]]
        if math.isinf(min_texture):
            region.copy_(target)
            continue
        decided = _texture_decides(
            _crop(img, 0, inner).contiguous(),
            {k: _crop(v, 0, inner).contiguous() for k, v in crop_terms.items()},
            _crop(alpha, 0, inner).contiguous(),
            _crop(cand, 0, inner).contiguous(),
            window,
            texture,
            min_texture,
            max_residual,
            _crop(_crop(flat_allowed, b, box), 0, inner),
        )
        _crop(region, 0, inner).copy_(_crop(target, 0, inner) & decided)
    return out


def _texture_decides(
    images: torch.Tensor,
    terms: dict[str, torch.Tensor],
    alpha: torch.Tensor,
    inside: torch.Tensor,
    window: int,
    texture: float,
    min_texture: float,
    max_residual: float,
    flat_allowed: torch.Tensor | None,
) -> torch.Tensor:
    """Test 3 of the module docstring at every pixel, the windows over the candidates
    ``inside`` (B, 1, H, W) bool; ``terms`` from :func:`_background_terms` (cropped alike)."""
    g_img = _luma_gradients(images.mean(1, keepdim=True))
    g_bg, energy, var = terms["g_bg"], terms["energy"], terms["var"]
    # what attenuation of the background does not explain
    diff = g_img.sub(g_bg * alpha)
    unexplained = diff[:, 0:1] * diff[:, 0:1]
    unexplained.addcmul_(diff[:, 1:2], diff[:, 1:2])
    # the windows average over the candidates only (shadow-like by colour, and foreground where
    # given), so that the person's pixels and the untouched background next to a candidate do
    # not enter its statistics; the statistics are written in place into one tensor
    n, _, h, w = images.shape
    stats = torch.empty(n, 7, h, w, dtype=images.dtype, device=images.device)
    inside = stats[:, 0:1].copy_(inside)
    # one step of a robust (Cauchy-weighted) regression: a gradient far larger than attenuated
    # texture plus noise would give, the edge of the shadow itself, hardly counts in the slope
    a2 = alpha * alpha
    scale = torch.addcmul(var, a2, energy).mul_(4.0)
    weight = torch.div(unexplained, scale, out=stats[:, 1:2]).add_(1.0)
    torch.div(inside, weight, out=weight)
    cross = torch.mul(g_img[:, 0:1], g_bg[:, 0:1], out=stats[:, 2:3])
    cross.addcmul_(g_img[:, 1:2], g_bg[:, 1:2]).mul_(weight)
    torch.mul(weight, energy, out=stats[:, 3:4])
    torch.mul(diff, inside, out=stats[:, 4:6])
    torch.mul(unexplained, inside, out=stats[:, 6:7])
    means = _box_sums(stats, window)  # sums, not means: only their ratios enter below
    support, robust = means[:, 0:1].clamp_min(1e-6), means[:, 1:2].clamp_min(1e-6)
    cross, energy = means[:, 2:3] / robust, means[:, 3:4] / robust
    # the spread of the unexplained gradients: a smooth change of the attenuation (a penumbra)
    # has about one gradient over the window, a person's texture or shading many
    spread = means[:, 6:7] / support - (means[:, 4:6] / support).square().sum(1, keepdim=True)
    residual = spread.clamp_min(0.0)
    # the luma's gradient noise: a central difference of a mean of 3 channels, x and y together,
    # has variance sigma^2 / 3 at most (independent channels); take sigma^2 (JPEG and demosaicing
    # correlate the channels)
    textured = a2 * energy >= min_texture * var
    slope = cross / energy.clamp_min(1e-12)
    flat = residual <= max_residual * var
    if flat_allowed is not None:
        flat = flat & flat_allowed
    return torch.where(textured, slope >= texture * alpha, flat)


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
