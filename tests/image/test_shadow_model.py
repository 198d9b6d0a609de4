"""The shadow model everywhere in the frame: attenuation, noise-scaled chromaticity, texture.

Hand-built scenes: a textured wall (sinusoids of several periods and orientations plus a
smoothed random pattern), a cast shadow that keeps its texture, a person patch of another
texture or a flat colour, a self-shadow on the person, and backgrounds of different noise.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from image_testing import quantise

from torchfit.image import SegmentationOptions, fit_background, segment, shadow_mask

H, W = 96, 128


def _texture(seed: int, contrast: float = 0.12, freq: float = 1.0) -> torch.Tensor:
    """(H, W) multiplicative texture around 1: sinusoids (frequencies scaled by ``freq``) and a
    smoothed random field."""
    gen = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    phase = torch.rand(3, generator=gen) * 2 * math.pi
    t = torch.sin(xx * 0.9 * freq + phase[0]) + torch.sin(yy * 0.7 * freq + phase[1])
    t = t + torch.sin((xx - yy) * 0.5 * freq + phase[2])
    noise = torch.rand(1, 1, H // 4, W // 4, generator=gen)
    noise = torch.nn.functional.interpolate(noise, size=(H, W), mode="bilinear")[0, 0]
    return 1 + contrast * (t / 3 + 2 * (noise - 0.5))


def _wall(seed: int = 0) -> torch.Tensor:
    """(3, H, W) a beige textured wall."""
    return torch.tensor([0.70, 0.62, 0.50]).view(3, 1, 1) * _texture(seed)


def _frames(scene: torch.Tensor, sigma: float, n: int = 6, seed: int = 1) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    noise = torch.randn(n, *scene.shape, generator=gen) * sigma
    return quantise((scene + noise).clamp(0, 1))


def _shot(image: torch.Tensor, sigma: float, seed: int = 2) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return quantise((image + torch.randn(image.shape, generator=gen) * sigma).clamp(0, 1))[None]


def _box(y0: int, y1: int, x0: int, x1: int) -> torch.Tensor:
    m = torch.zeros(H, W, dtype=torch.bool)
    m[y0:y1, x0:x1] = True
    return m


def test_textured_shadow_is_background_and_person_patches_are_not() -> None:
    wall = _wall()
    frames = _frames(wall, 2 / 255)
    image = wall.clone()
    shadow = _box(10, 80, 70, 120)
    image[:, shadow] *= 0.55  # a deep cast shadow: darker, same colour, same texture
    # a person patch of another texture, darker than the wall with the wall's colour (what
    # chromaticity alone calls a shadow), and one of a flat colour, also the wall's, darker
    other = torch.tensor([0.70, 0.62, 0.50]).view(3, 1, 1) * 0.6 * _texture(7, freq=0.37)
    textured_person, flat_person = _box(10, 80, 8, 30), _box(10, 80, 38, 60)
    image[:, textured_person] = other[:, textured_person]
    image[:, flat_person] = torch.tensor([0.70, 0.62, 0.50]).view(3, 1) * 0.6
    image = _shot(image, 2 / 255)
    cfg = SegmentationOptions(largest_region=False)
    model = fit_background(frames, cfg)
    got = shadow_mask(model, image)[0, 0]
    inner = _box(14, 76, 74, 116)  # away from the shadow's border
    assert float(got[inner].float().mean()) > 0.97
    # the person patches fail the texture test except within a few pixels of their border
    for patch in (textured_person, flat_person):
        core = patch & ~torch.roll(~patch, 4, 0) & ~torch.roll(~patch, -4, 0)
        core &= ~torch.roll(~patch, 4, 1) & ~torch.roll(~patch, -4, 1)
        assert float(got[core].float().mean()) < 0.02
    # chromaticity alone (texture off) takes both person patches for a shadow
    colour_only = shadow_mask(model, image, min_texture=float("inf"))[0, 0]
    assert float(colour_only[flat_person].float().mean()) > 0.9
    # the whole chain: shadow background, both patches person (but for a pixel or two along
    # their borders)
    mask = segment(image, model, cfg).masks[0, 0]
    assert float(mask[shadow].float().mean()) < 0.03
    assert float(mask[textured_person | flat_person].float().mean()) > 0.95


def test_soft_shadow_on_textured_wall_and_on_flat_wall() -> None:
    flat = torch.tensor([0.55, 0.55, 0.60]).view(3, 1, 1).expand(3, H, W)
    # what is left of the shadow disc (penumbra included) after clean-up: a few small blobs
    # along the penumbra of the textured wall (where the attenuation changes within the
    # texture window), nothing on the flat wall
    for wall, left in ((_wall(3), 0.1), (flat, 0.01)):
        frames = _frames(wall, 1.5 / 255)
        yy, xx = np.mgrid[0:H, 0:W]
        # a disc of shadow with a penumbra 6 px wide: attenuation 0.5 inside, 1 outside
        r = np.hypot(yy - 48, xx - 64)
        att = torch.from_numpy(0.5 + 0.5 * np.clip((r - 25) / 6, 0, 1)).float()
        image = _shot(wall * att, 1.5 / 255)
        # the flat-background decision everywhere (by default only in the lower half of the
        # foreground, where a floor shadow lies)
        cfg = SegmentationOptions(largest_region=False, shadow_flat_band=1.0)
        result = segment(image, fit_background(frames, cfg), cfg)
        disc = torch.from_numpy(r < 31)
        assert float(result.masks[0, 0].sum()) <= left * float(disc.sum())


def test_self_shadow_on_the_person_stays_person() -> None:
    wall = _wall(4)
    frames = _frames(wall, 2 / 255)
    person = _box(8, 90, 40, 80)
    shirt = torch.tensor([0.25, 0.35, 0.75]).view(3, 1, 1) * _texture(9, contrast=0.05)
    image = wall.clone()
    lit = shirt.clone()
    lit[:, 50:, :] *= 0.55  # the lower half of the person in its own shadow
    image[:, person] = lit[:, person]
    cast = _box(20, 90, 80, 110)  # and its shadow on the wall beside it
    image[:, cast] *= 0.6
    image = _shot(image, 2 / 255)
    cfg = SegmentationOptions()
    result = segment(image, fit_background(frames, cfg), cfg)
    mask = result.masks[0, 0]
    assert float(mask[person].float().mean()) > 0.99
    assert float(mask[cast].float().mean()) < 0.05
    assert not bool(result.shadow[0, 0][person].any())


def test_allowed_colour_distortion_scales_with_the_background_noise() -> None:
    # a flat wall, steady on the left half, noisy on the right (10 levels standard deviation)
    wall = torch.tensor([0.60, 0.50, 0.40]).view(3, 1, 1).expand(3, H, W).clone()
    sigma = torch.full((1, H, W), 0.5 / 255)
    sigma[..., W // 2 :] = 10 / 255
    gen = torch.Generator().manual_seed(0)
    frames = quantise((wall + torch.randn(20, 3, H, W, generator=gen) * sigma).clamp(0, 1))
    model = fit_background(frames)
    # the per-pixel variance: the sample variance over the frames, mean of the channels,
    # averaged over 5 x 5 pixels (a naive loop as the reference)
    raw = frames.double().var(0).mean(0).numpy()
    ref = np.empty_like(raw)
    for y in range(H):
        for x in range(W):
            ref[y, x] = raw[max(y - 2, 0) : y + 3, max(x - 2, 0) : x + 3].mean()
    torch.testing.assert_close(
        model.rgb_var[0, 0].double(), torch.from_numpy(ref), rtol=1e-4, atol=1e-9
    )
    # the same distortion everywhere: 0.7 of the wall plus a colour shift off its colour line
    # of 0.03 (about 8 levels), steady on the image
    shift = torch.tensor([0.02, -0.0, -0.0224]).view(3, 1, 1)
    image = quantise((wall * 0.7 + shift).clamp(0, 1))[None]
    got = shadow_mask(model, image, max_angle=0.0, noise=3.0)[0, 0]
    assert not bool(got[:, 2 : W // 2 - 3].any())  # steady background: a real colour change
    assert bool(got[:, W // 2 + 3 : -2].all())  # noisy background: within its noise
    # with more noise allowed the steady half passes too, with none the noisy half fails
    assert bool(shadow_mask(model, image, max_angle=0.0, noise=50.0).all())
    assert not bool(shadow_mask(model, image, max_angle=0.0, noise=0.0).any())


def test_shadow_mask_checks_its_arguments() -> None:
    frames = _frames(_wall(), 2 / 255)
    model = fit_background(frames)
    image = frames[:1]
    with pytest.raises(ValueError, match="window must be odd"):
        shadow_mask(model, image, window=4)
    with pytest.raises(ValueError, match="must be >= 0"):
        shadow_mask(model, image, noise=-1.0)
    # a background model without noise estimate falls back to the quantisation floor
    bare = type(model)(model.mean, model.covariance, rgb_mean=model.rgb_mean)
    assert bare.rgb_var is None
    assert shadow_mask(bare, image).shape == (1, 1, H, W)
