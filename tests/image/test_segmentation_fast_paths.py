"""The fast paths of the segmentation chain against straightforward references.

On the CPU in float32 the colour features go through OpenCV, the colour test runs image by
image, the shadow test runs on boxes around the pixels to decide with box sums from OpenCV and
background terms kept with the model. Each is compared here with a plain whole-frame
computation in float64 (written out below, or through the torch path the other dtypes take).
"""

from __future__ import annotations

import colorsys
import math

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from image_testing import quantise

from torchfit.image import (
    SegmentationOptions,
    color_features,
    fit_background,
    mahalanobis_distance,
    segment,
    shadow_mask,
)
from torchfit.image.morphology import binary_opening
from torchfit.image.shadow import _background_terms, _box_sums

H, W = 90, 120


def _scene(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Background frames (6, 3, H, W), two images (2, 3, H, W) and the person (2, H, W): a
    textured wall and a flat floor, a person of flat and textured clothing, a cast shadow
    across wall and floor, speckles of noise."""
    gen = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    tone = 1 + 0.15 * torch.sin(xx * 0.8) * torch.cos(yy * 0.5)
    wall = torch.tensor([0.7, 0.6, 0.5]).view(3, 1, 1) * tone
    wall[:, 60:] = torch.tensor([0.45, 0.40, 0.35]).view(3, 1, 1)  # flat floor
    frames = quantise((wall + 0.01 * torch.randn(6, 3, H, W, generator=gen)).clamp(0, 1))
    images, person = [], torch.zeros(2, H, W, dtype=torch.bool)
    for i in range(2):
        img = wall.clone()
        img[:, 30 + 5 * i : 85, 70:110] *= 0.55  # the cast shadow, wall and floor
        person[i, 10 : 80 - 5 * i, 40 + 3 * i : 70] = True
        img[:, person[i]] = torch.tensor([0.3, 0.35, 0.6]).view(3, 1)
        img[:, 40:60, 45:60] = 0.5 * wall[:, 40:60, 45:60]  # clothing: a darker copy of the wall
        img = img + 0.012 * torch.randn(3, H, W, generator=gen)
        images.append(quantise(img.clamp(0, 1)))
    return frames, torch.stack(images), person


def test_opencv_colour_features_match_colorsys() -> None:
    gen = torch.Generator().manual_seed(0)
    img = quantise(torch.rand(1, 3, 6, 7, generator=gen))
    img[0, :, 0, 0] = 0.5  # grey: zero saturation
    img[0, :, 0, 1] = 0.0
    img[0, :, 0, 2] = 1.0
    img[0, :, 1, 0] = torch.tensor([1.0, 0.0, 0.0])
    img[0, :, 1, 1] = torch.tensor([0.2, 0.9, 0.9])  # light: HLS saturation above L = 1/2
    gamma = 0.7
    f = color_features(img, "hsl", gamma)
    assert f.dtype == torch.float32 and f.shape == img.shape
    for y in range(6):
        for x in range(7):
            h, light, s = colorsys.rgb_to_hls(*img[0, :, y, x].double().tolist())
            ref = [255 * s * math.cos(2 * math.pi * h), 255 * s * math.sin(2 * math.pi * h)]
            ref.append(255 * gamma * light)
            np.testing.assert_allclose(f[0, :, y, x].numpy(), ref, atol=2e-3)
    # a batch of frames (B, N, 3, H, W) the same as one by one, and as the float64 path
    frames = quantise(torch.rand(2, 3, 3, 5, 4, generator=gen))
    batched = color_features(frames, "hsl", 0.3)
    torch.testing.assert_close(batched[1, 2], color_features(frames[1, 2], "hsl", 0.3))
    torch.testing.assert_close(
        batched.double(), color_features(frames.double(), "hsl", 0.3), atol=2e-3, rtol=0
    )


def test_colour_test_float32_equals_float64_image_by_image() -> None:
    frames, images, _ = _scene()
    for model_batch in (1, 2):
        f = frames.expand(model_batch, -1, -1, -1, -1)
        fast = mahalanobis_distance(fit_background(f), images)
        ref = mahalanobis_distance(fit_background(f.double()), images.double())
        assert fast.dtype == torch.float32 and fast.shape == (2, 1, H, W)
        torch.testing.assert_close(fast.double(), ref, rtol=1e-3, atol=1e-3)


def test_box_sums_from_opencv_equal_running_sums_and_pooling() -> None:
    gen = torch.Generator().manual_seed(2)
    x = torch.rand(2, 4, 23, 31, generator=gen)
    for window in (1, 3, 7):
        fast = _box_sums(x, window)
        slow = _box_sums(x.double(), window)
        pooled = F.avg_pool2d(x.double(), window, 1, window // 2) * window**2
        torch.testing.assert_close(fast.double(), slow, rtol=0, atol=1e-5)
        torch.testing.assert_close(slow, pooled, rtol=0, atol=1e-9)


def _reference_shadow(model, images, fg, opt: SegmentationOptions) -> torch.Tensor:
    """The shadow test of ``torchfit.image.shadow``'s docstring over the whole frame, float64,
    written out directly (distance to the colour line, pooled window means)."""
    bg = model.rgb_mean.double()
    var = model.rgb_var.double() + (1 / 255) ** 2
    img = images.double()
    bb = bg.square().sum(1, keepdim=True).clamp_min(1e-6)
    alpha = (img * bg).sum(1, keepdim=True) / bb
    off = (img - alpha * bg).norm(dim=1, keepdim=True)
    allowed = opt.shadow_chroma * alpha.clamp_min(0) * bb.sqrt()
    allowed = allowed + opt.shadow_noise * math.sqrt(2) * var.sqrt()
    low, high = opt.shadow_ratio
    cand = (alpha >= low) & (alpha <= high) & (off <= allowed) & fg

    def grads(x):
        p = F.pad(x.mean(1, keepdim=True), (1, 1, 1, 1), mode="replicate")
        gx = 0.5 * (p[..., 1:-1, 2:] - p[..., 1:-1, :-2])
        return torch.cat([gx, 0.5 * (p[..., 2:, 1:-1] - p[..., :-2, 1:-1])], 1)

    def mean(x):
        return F.avg_pool2d(x, opt.shadow_window, 1, opt.shadow_window // 2)

    g_i, g_b = grads(img), grads(bg)
    diff = g_i - alpha * g_b
    energy = g_b.square().sum(1, keepdim=True)
    inside = cand.double()
    w = inside / (1 + diff.square().sum(1, keepdim=True) / (4 * (alpha**2 * energy + var)))
    robust = mean(w).clamp_min(1e-6 / opt.shadow_window**2)
    support = mean(inside).clamp_min(1e-6 / opt.shadow_window**2)
    slope = mean(w * (g_i * g_b).sum(1, keepdim=True)) / mean(w * energy).clamp_min(1e-12)
    m_energy = mean(w * energy) / robust
    spread = mean(inside * diff.square().sum(1, keepdim=True)) / support
    spread = spread - (mean(inside * diff) / support).square().sum(1, keepdim=True)
    textured = alpha**2 * m_energy >= opt.shadow_min_texture * var
    flat = spread.clamp_min(0) <= opt.shadow_max_residual * var
    decided = torch.where(textured, slope >= opt.shadow_texture * alpha, flat)
    return cand & decided


def test_shadow_test_on_boxes_equals_the_whole_frame_reference() -> None:
    frames, images, _ = _scene(3)
    opt = SegmentationOptions()
    model = fit_background(frames, opt)
    fg = mahalanobis_distance(model, images) > opt.threshold
    within = binary_opening(fg, 3)
    ref = _reference_shadow(model, images, fg, opt)
    assert 200 < int((ref & within).sum()) < int(within.sum())  # shadow and person both there
    args = (opt.shadow_chroma, opt.shadow_noise, opt.shadow_window, opt.shadow_texture)
    args += (opt.shadow_min_texture, opt.shadow_max_residual)
    for dtype in (torch.float32, torch.float64):
        got = shadow_mask(model, images.to(dtype), opt.shadow_ratio, *args, fg, None, within)
        assert not bool((got & ~within).any())  # nothing decided outside `within`
        differ = int((got ^ (ref & within)).sum())
        assert differ <= 2, f"{dtype}: {differ} pixels differ"  # rounding at a threshold only
        # without `within` every foreground pixel is decided, as on the whole frame
        full = shadow_mask(model, images.to(dtype), opt.shadow_ratio, *args, fg)
        assert int((full ^ ref).sum()) <= 2


def test_background_terms_are_computed_once_per_model_and_dtype() -> None:
    frames, images, _ = _scene()
    model = fit_background(frames)
    first = _background_terms(model, torch.float32)
    assert _background_terms(model, torch.float32) is first
    assert _background_terms(model, torch.float64).dtype == torch.float64
    calls = []
    assert model.cached("k", lambda m: calls.append(m) or 7) == 7
    assert model.cached("k", lambda m: calls.append(m) or 8) == 7 and len(calls) == 1
    # a model on another device (or a copy) starts without them
    assert model.to("cpu")._cache == {}


def test_segmentation_float32_fast_path_equals_float64_torch_path() -> None:
    frames, images, person = _scene(5)
    opt = SegmentationOptions()
    fast = segment(images, fit_background(frames, opt), opt)
    slow = segment(images.double(), fit_background(frames.double(), opt), opt)
    differ = (fast.masks ^ slow.masks).flatten(1).sum(1)
    assert bool((differ <= 3).all()), differ
    assert bool((fast.shadow ^ slow.shadow).flatten(1).sum(1).le(3).all())
    # and it found the person, but for the clothing that is a darker copy of the textured wall
    # (which no local test tells from a cast shadow)
    person[:, 40:60, 45:60] = False
    inter = (fast.masks[:, 0] & person).flatten(1).sum(1).double()
    assert bool((inter / person.flatten(1).sum(1) > 0.95).all())
