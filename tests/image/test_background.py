"""Colour features, the background model and the Mahalanobis test.

Independent references: ``colorsys`` (Python's own RGB -> HLS), NumPy's ``np.cov`` and
``np.linalg.solve`` per pixel, and a synthetic cast shadow.
"""

from __future__ import annotations

import colorsys
import math
import shutil

import kornia
import numpy as np
import pytest
import torch
from image_testing import quantise

from torchfit.errors import SegmentationError, ShapeError
from torchfit.image import (
    SegmentationOptions,
    color_features,
    fit_background,
    mahalanobis_distance,
    segment,
)


def test_color_features_match_colorsys() -> None:
    gen = torch.Generator().manual_seed(0)
    img = quantise(torch.rand(1, 3, 4, 5, generator=gen, dtype=torch.float64))
    img[0, :, 0, 0] = 0.5  # grey: zero saturation
    gamma = 0.4
    f = color_features(img, "hsl", gamma)
    for y in range(4):
        for x in range(5):
            h, l, s = colorsys.rgb_to_hls(*img[0, :, y, x].tolist())
            ref = [255 * s * math.cos(2 * math.pi * h), 255 * s * math.sin(2 * math.pi * h)]
            ref.append(255 * gamma * l)
            np.testing.assert_allclose(f[0, :, y, x].numpy(), ref, atol=1e-4)
    torch.testing.assert_close(color_features(img, "rgb"), img * 255)
    with pytest.raises(ValueError, match="gamma must be in"):
        color_features(img, "hsl", 1.5)
    with pytest.raises(ValueError, match="color_space must be"):
        color_features(img, "lab")


def test_background_mean_covariance_and_distance_match_numpy() -> None:
    gen = torch.Generator().manual_seed(1)
    frames = quantise(0.2 + 0.6 * torch.rand(2, 7, 3, 4, 6, generator=gen, dtype=torch.float64))
    cfg = SegmentationOptions(gamma=0.5, regularization=2.0)
    model = fit_background(frames, cfg)
    images = quantise(torch.rand(2, 3, 4, 6, generator=gen, dtype=torch.float64))
    dist = mahalanobis_distance(model, images)
    assert model.mean.shape == (2, 3, 4, 6) and dist.shape == (2, 1, 4, 6)
    feats = color_features(frames, "hsl", 0.5).numpy()
    test = color_features(images, "hsl", 0.5).numpy()
    for b in range(2):
        for y in range(4):
            for x in range(6):
                samples = feats[b, :, :, y, x]  # (N, 3)
                mu = samples.mean(0)
                cov = np.cov(samples, rowvar=False) + 2.0 * np.eye(3)
                np.testing.assert_allclose(model.mean[b, :, y, x].numpy(), mu, atol=1e-9)
                np.testing.assert_allclose(model.covariance[b, :, :, y, x].numpy(), cov, atol=1e-8)
                diff = test[b, :, y, x] - mu
                ref = math.sqrt(diff @ np.linalg.solve(cov, diff))
                assert dist[b, 0, y, x].item() == pytest.approx(ref, rel=1e-9)


@pytest.mark.skipif(
    not any(shutil.which(c) for c in ("c++", "g++", "clang++")),
    reason="torch.compile on CPU needs a C++ compiler",
)
def test_compiled_colour_test_equals_eager() -> None:
    """segmentation.compile: the fused kernel gives the eager distances (float32 rounding)."""
    gen = torch.Generator().manual_seed(5)
    frames = quantise(0.1 + 0.8 * torch.rand(6, 3, 24, 40, generator=gen))
    model = fit_background(frames, SegmentationOptions(gamma=0.7))
    images = quantise(torch.rand(3, 3, 24, 40, generator=gen))
    images[0, :, :4, :4] = 0.5  # grey: zero chroma, the hue's guarded division
    eager = mahalanobis_distance(model, images)
    compiled = mahalanobis_distance(model, images, compiled=True)
    torch.testing.assert_close(compiled, eager, rtol=1e-4, atol=1e-3)
    masks = segment(images, model, SegmentationOptions(gamma=0.7)).masks
    fused = segment(images, model, SegmentationOptions(gamma=0.7, compile=True)).masks
    assert (masks != fused).float().mean() < 1e-3  # only ties at the threshold may differ


def test_temporal_median_matches_reference_and_ignores_the_person() -> None:
    gen = torch.Generator().manual_seed(2)
    h, w, n = 24, 32, 9
    scene = 0.3 + 0.3 * torch.rand(1, 3, h, w, generator=gen, dtype=torch.float64)
    frames = quantise(scene + torch.randn(n, 3, h, w, generator=gen, dtype=torch.float64) / 255)
    for i in range(n):  # a person walking across: present in every frame, never in one place
        frames[i, :, 8:18, 3 * i : 3 * i + 5] = torch.tensor([0.9, 0.1, 0.1]).view(3, 1, 1)
    cfg = SegmentationOptions(background="temporal_median", gamma=0.3)
    model = fit_background(frames, cfg)
    feats = color_features(frames, "hsl", 0.3).numpy()
    y, x = 10, 7  # covered by the person in frames 1 and 2
    samples = feats[:, :, y, x]
    med = np.median(samples, axis=0)
    keep = samples[np.argsort(((samples - med) ** 2).sum(1), kind="stable")[:5]]
    cov = np.cov(keep, rowvar=False) * 2.4574 + np.eye(3)
    np.testing.assert_allclose(model.mean[0, :, y, x].numpy(), keep.mean(0), atol=1e-9)
    np.testing.assert_allclose(model.covariance[0, :, :, y, x].numpy(), cov, rtol=1e-6)
    # The clean scene is background everywhere; the person is found where it stands.
    assert float(mahalanobis_distance(model, quantise(scene)).max()) < cfg.threshold
    res = segment(frames[4:5].float(), model.to("cpu"), cfg)
    assert bool(res.found[0])
    truth = torch.zeros(h, w, dtype=torch.bool)
    truth[8:18, 12:17] = True
    assert (res.masks[0, 0] & truth).sum() / truth.sum() > 0.95
    assert (res.masks[0, 0] & ~truth).sum() < 5


def test_background_errors() -> None:
    frames = torch.rand(4, 3, 8, 8)
    with pytest.raises(SegmentationError, match="at least 5 background frames.*got 4"):
        fit_background(frames)
    model = fit_background(frames, SegmentationOptions(min_background_frames=4))
    with pytest.raises(SegmentationError, match=r"expected size 8x8 .*got 9x8"):
        mahalanobis_distance(model, torch.rand(1, 3, 8, 9))
    with pytest.raises(ShapeError, match=r"images: expected shape \(B, 3, H, W\)"):
        mahalanobis_distance(model, torch.rand(3, 8, 8))
    with pytest.raises(ShapeError, match=r"frames: expected shape \(B, N, 3, H, W\)"):
        fit_background(torch.rand(5, 4, 8, 8))
    with pytest.raises(ShapeError, match="float tensor"):
        fit_background(torch.zeros(5, 3, 8, 8, dtype=torch.uint8))
    two = fit_background(torch.rand(2, 5, 3, 8, 8), SegmentationOptions())
    with pytest.raises(SegmentationError, match="batch 3 does not match"):
        mahalanobis_distance(two, torch.rand(3, 3, 8, 8))


def shadow_scene(k: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Textured background (HLS lightness 0.25-0.45, saturation 0.3-0.8), sensor noise of 2
    levels, a person and a cast shadow beside the feet that darkens the floor by ``1 - k``."""
    gen = torch.Generator().manual_seed(0)
    h = w = 96

    def smooth(lo: float, hi: float) -> torch.Tensor:
        x = torch.rand(1, 1, 6, 6, generator=gen)
        x = torch.nn.functional.interpolate(x, size=(h, w), mode="bilinear", align_corners=False)
        return lo + (hi - lo) * x

    hls = torch.cat([smooth(0, 2 * math.pi), smooth(0.25, 0.45), smooth(0.3, 0.8)], 1)
    scene = kornia.color.hls_to_rgb(hls)

    def noisy(img: torch.Tensor, n: int) -> torch.Tensor:
        return quantise(
            img.expand(n, -1, -1, -1) + torch.randn(n, 3, h, w, generator=gen) * 2 / 255
        )

    person = torch.zeros(h, w, dtype=torch.bool)
    person[10:80, 20:40] = True
    shadow = torch.zeros(h, w, dtype=torch.bool)
    shadow[60:80, 40:90] = True
    img = scene.clone()
    img[:, :, shadow] *= k  # same hue, darker
    img[:, :, person] = torch.tensor([0.85, 0.8, 0.75]).view(1, 3, 1)
    return noisy(scene, 10), noisy(img, 1), person, shadow


@pytest.mark.parametrize("k", [0.7, 0.6, 0.5])
def test_hsl_keeps_cast_shadow_as_background_rgb_baseline_does_not(k: float) -> None:
    background, image, person, shadow = shadow_scene(k)
    results = {}
    for space in ("hsl", "rgb"):
        # brightness barely weighted (gamma = 0.05), as the paper allows; the colour test alone
        cfg = SegmentationOptions(gamma=0.05, color_space=space, shadow_test=False, edge_width=0)
        model = fit_background(background, cfg)
        res = segment(image, model, cfg)
        raw = (res.distance[0, 0][shadow] <= cfg.threshold).float().mean().item()
        cleaned = (~res.masks[0, 0][shadow]).float().mean().item()
        recall = res.masks[0, 0][person].float().mean().item()
        results[space] = (raw, cleaned, recall)
    hsl, rgb = results["hsl"], results["rgb"]
    assert hsl[1] >= 0.95, results  # after clean-up: shadow kept as background
    assert hsl[0] >= 0.6, results  # the pixel test alone already keeps most of it
    assert rgb[0] <= 0.01 and rgb[1] <= 0.05, results  # the RGB baseline takes it as person
    assert hsl[2] >= 0.99 and rgb[2] >= 0.99, results  # both find the person
