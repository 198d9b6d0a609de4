"""The explicit cast-shadow test, its lower band and the bridge, on hand-built scenes.

(The texture and noise parts of the shadow model: ``test_shadow_model.py``.)
"""

from __future__ import annotations

import pytest
import torch
from image_testing import COLOUR_SHADOW, quantise, shin_scene

from torchfit.errors import ConfigError, SegmentationError
from torchfit.image import (
    SegmentationOptions,
    fit_background,
    segment,
    shadow_mask,
)


def _legs_scene(shadow: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A textured brown floor, two "legs" on it and, optionally, a cast shadow (the floor
    scaled by 0.7 in each channel, same hue) that joins the feet. Returns background frames
    (5, 3, H, W), the image (1, 3, H, W) and the true person mask (H, W)."""
    gen = torch.Generator().manual_seed(3)
    h, w = 80, 80
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    tone = 1 + 0.08 * torch.sin(xx * 0.7) * torch.cos(yy * 0.3)
    floor = torch.tensor([0.55, 0.40, 0.25]).view(3, 1, 1) * tone
    frames = (floor + 0.006 * torch.randn(5, 3, h, w, generator=gen)).clamp(0, 1)
    person = torch.zeros(h, w, dtype=torch.bool)
    person[5:60, 20:60] = True  # trunk and hips
    person[60:75, 20:32] = True  # left leg
    person[60:75, 48:60] = True  # right leg
    person[30:60, 32:48] = False  # the gap between the legs, open at the bottom
    image = floor.clone()
    if shadow:
        image[:, 62:78, 10:75] *= 0.7  # across and below the feet
    image[:, person] = torch.tensor([0.2, 0.3, 0.7]).view(3, 1)  # blue clothing
    image = (image + 0.006 * torch.randn(3, h, w, generator=gen)).clamp(0, 1)
    return quantise(frames), quantise(image)[None], person


def test_shadow_test_keeps_the_leg_gap_and_drops_the_shadow() -> None:
    frames, image, person = _legs_scene(shadow=True)
    shadow = torch.zeros_like(person)
    shadow[62:78, 10:75] = True
    shadow &= ~person
    base = SegmentationOptions(gamma=0.3, threshold=4.0, shadow_test=False)
    model = fit_background(frames, base)
    plain = segment(image, model, base).masks[0, 0]
    # without the shadow test the shadow is person and joins the feet: the gap is filled
    assert float(plain[shadow].float().mean()) > 0.5
    assert bool(plain[35:60, 36:44].all())
    assert not bool(segment(image, model, base).shadow.any())  # no shadow test, no flags
    cfg = SegmentationOptions(gamma=0.3, threshold=4.0, shadow_test=True, max_hole_area=0.02)
    result = segment(image, fit_background(frames, cfg), cfg)
    got = result.masks[0, 0]
    assert float(got[shadow].float().mean()) < 0.02  # the shadow is background
    # ... and flagged as what the shadow test removed (inside its band: the lowest quarter)
    flagged = result.shadow[0, 0]
    assert float(flagged[shadow].float().mean()) > 0.9 and not bool(flagged[person].any())
    assert not bool(got[35:60, 36:44].any())  # the leg gap survives
    assert float((got == person).float().mean()) > 0.98
    # the shadow test alone, against a darker object of another colour
    s = shadow_mask(model, image)[0, 0]
    assert float(s[shadow].float().mean()) > 0.95 and not bool(s[person].any())


def test_shadow_bridge_keeps_shins_of_the_floor_colour_between_knee_and_shoe() -> None:
    # Grey floor; blue trunk and thighs; shins a darker copy of the floor (what the shadow test
    # calls shadow); black shoes; a real cast shadow on the floor beside the feet.
    scene = shin_scene()
    frames, image = scene["frames"], scene["image"]
    body, shins, shoes, cast = scene["body"], scene["shins"], scene["shoes"], scene["cast"]
    person = body | shins | shoes
    # colour alone (no texture test, the earlier model): the shins pass as shadow
    base = COLOUR_SHADOW
    cut = SegmentationOptions(**base)
    model = fit_background(frames, cut)
    without = segment(image, model, cut)
    # the shins pass as shadow: the shoes are cut off and dropped with them
    assert not bool(without.masks[0, 0][shoes].any())
    assert float(without.shadow[0, 0][shins].float().mean()) > 0.9
    bridged = SegmentationOptions(**base, shadow_bridge=True)
    got = segment(image, model, bridged)
    mask = got.masks[0, 0]
    assert float(mask[shins | shoes].float().mean()) > 0.97
    assert float(mask[cast].float().mean()) < 0.02  # the cast shadow stays background
    assert not bool(mask[40:75, 32:40].any())  # and so does the gap between the legs
    assert not bool(got.shadow[0, 0][shins].any())
    assert float((mask == person).float().mean()) > 0.98


def test_shadow_test_leaves_unshadowed_scene_alone_and_checks_input() -> None:
    frames, image, person = _legs_scene(shadow=False)
    cfg = SegmentationOptions(gamma=0.3, shadow_test=True)
    model = fit_background(frames, cfg)
    got = segment(image, model, cfg).masks[0, 0]
    assert float((got == person).float().mean()) > 0.98
    assert model.rgb_mean is not None and model.rgb_mean.shape == (1, 3, 80, 80)
    median = fit_background(frames, SegmentationOptions(background="temporal_median"))
    assert torch.allclose(median.rgb_mean, model.rgb_mean, atol=0.02)
    with pytest.raises(ValueError, match="ratio must satisfy"):
        shadow_mask(model, image, (0.9, 0.5))
    with pytest.raises(SegmentationError, match="expected size"):
        shadow_mask(model, image[..., :40])
    with pytest.raises(ConfigError, match="shadow_ratio"):  # when the options are made
        SegmentationOptions(shadow_test=True, shadow_ratio=(0.5,))
