"""Photometric compensation: per-channel gains between the background frames and a frame.

Independent reference: the gains the synthetic scenes are made with, and the mask of the same
scene without any change of exposure or white balance.
"""

from __future__ import annotations

import dataclasses

import kornia
import pytest
import torch
from image_testing import quantise

from torchfit.errors import SegmentationError, ShapeError
from torchfit.image import SegmentationOptions, fit_background, segment
from torchfit.image.photometric import compensate, estimate_gains, match_background

H, W = 120, 160
GAINS = [
    (1.15, 1.15, 1.15),  # brighter exposure
    (0.85, 0.85, 0.85),  # darker exposure
    (1.15, 1.0, 0.85),  # warmer white balance
    (0.85, 1.0, 1.15),  # cooler white balance
    (1.15, 0.85, 1.15),
    (0.87, 1.12, 0.9),
]


def _scene(gen: torch.Generator):
    """A textured room (with a near-white patch that a brighter exposure clips), a person with
    a cast shadow; the noise-free background (1, 3, H, W), the person mask and a function that
    renders noisy, 8-bit frames with given gains."""
    coarse = torch.rand(1, 3, 6, 8, generator=gen)
    hls = torch.nn.functional.interpolate(coarse, size=(H, W), mode="bilinear")
    hls = torch.cat([hls[:, :1] * 6.28, 0.2 + 0.5 * hls[:, 1:2], 0.2 + 0.5 * hls[:, 2:]], 1)
    room = kornia.color.hls_to_rgb(hls)
    room[:, :, 5:30, 100:150] = torch.tensor([0.95, 0.93, 0.9]).view(1, 3, 1, 1)  # a lamp
    person = torch.zeros(H, W, dtype=torch.bool)
    person[20:110, 60:80] = True  # trunk and legs
    person[8:20, 64:76] = True  # head
    person[35:42, 40:100] = True  # arms
    scene = room.clone()
    scene[:, :, 100:115, 80:130] *= 0.6  # cast shadow on the floor
    scene[:, :, person] = torch.tensor([0.75, 0.3, 0.25]).view(1, 3, 1)

    def render(img: torch.Tensor, gains, n: int = 1) -> torch.Tensor:
        g = torch.tensor(gains).view(1, 3, 1, 1)
        noisy = img * g + torch.randn(n, 3, H, W, generator=gen) * 1.5 / 255
        return quantise(noisy.clamp(0, 1))

    return room, scene, person, render


def _f_measure(a: torch.Tensor, b: torch.Tensor) -> float:
    tp = float((a & b).sum())
    return 2 * tp / max(float(a.sum() + b.sum()), 1.0)


@pytest.fixture(scope="module")
def scene():
    gen = torch.Generator().manual_seed(0)
    room, img, person, render = _scene(gen)
    frames = render(room, (1, 1, 1), 6)
    options = SegmentationOptions(shadow_test=True, shadow_band=0.25)
    model = fit_background(frames, options)
    reference = segment(render(img, (1, 1, 1)), model, options).masks[0, 0]
    return img, person, render, model, options, reference


def test_reference_mask_is_the_person(scene) -> None:
    _, person, _, _, _, reference = scene
    assert _f_measure(reference, person) > 0.98


@pytest.mark.parametrize("gains", GAINS)
def test_gains_are_estimated_and_undone(scene, gains) -> None:
    img, _, render, model, options, reference = scene
    frame = render(img, gains)
    est = estimate_gains(frame, model.rgb_mean)
    assert bool(est.estimated[0])
    torch.testing.assert_close(est.gains[0], torch.tensor(gains), rtol=0.01, atol=0.0)
    result = segment(frame, model, options)
    assert _f_measure(result.masks[0, 0], reference) >= 0.99
    torch.testing.assert_close(result.gains, est.gains)  # applied: the test noticed it
    # without the compensation the same frame is lost (the test above is not vacuous)
    off = segment(frame, model, dataclasses.replace(options, photometric=False))
    assert _f_measure(off.masks[0, 0], reference) < 0.9


def test_a_slow_drift_is_followed_frame_by_frame(scene) -> None:
    """Exposure and white balance drifting over a capture: each frame has its own gains."""
    img, _, render, model, options, reference = scene
    steps = torch.linspace(0, 1, 8)
    drift = [(1 + 0.15 * t, 1 - 0.05 * t, 1 - 0.15 * t) for t in steps.tolist()]
    frames = torch.cat([render(img, g) for g in drift])
    est = estimate_gains(frames, model.rgb_mean)
    torch.testing.assert_close(est.gains, torch.tensor(drift), rtol=0.01, atol=0.0)
    result = segment(frames, model, options)
    for i in range(len(drift)):
        assert _f_measure(result.masks[i, 0], reference) >= 0.99, i
    # the last frames are undone (their change matters to the colour test), the first is not
    torch.testing.assert_close(result.gains[-1], torch.tensor(drift[-1]), rtol=0.01, atol=0.0)
    torch.testing.assert_close(result.gains[0], torch.ones(3))


def test_unchanged_frames_are_left_as_they_are(scene) -> None:
    img, _, render, model, options, reference = scene
    frame = render(img, (1, 1, 1))
    est = estimate_gains(frame, model.rgb_mean)
    torch.testing.assert_close(est.gains[0], torch.ones(3), rtol=0.005, atol=0.0)
    out = compensate(frame, model.rgb_mean, torch.ones(1, 3))
    torch.testing.assert_close(out, frame)
    # a gain the colour test does not notice is not applied: the frame is segmented as is
    matched, result = match_background(frame, model)
    assert bool(result.estimated[0]) and not bool(result.applied[0])
    assert abs(float(result.effect[0])) < 0.01
    assert matched is frame
    torch.testing.assert_close(result.undone, torch.ones(1, 3))


def test_clipped_pixels_take_the_background_value() -> None:
    """A 255 says only "at least this bright": where that is consistent with the background,
    the compensated value is the background's."""
    bg = torch.tensor([0.9, 0.5, 0.2]).view(1, 3, 1, 1)
    image = torch.tensor([1.0, 0.575, 0.23]).view(1, 3, 1, 1)  # gain 1.15, red clipped
    out = compensate(image, bg, torch.full((1, 3), 1.15))
    torch.testing.assert_close(out.view(3), torch.tensor([0.9, 0.5, 0.2]))
    white = torch.ones(1, 3, 1, 1)  # a white shirt in front of a grey wall stays white-ish
    out = compensate(white, torch.full((1, 3, 1, 1), 0.4), torch.full((1, 3), 1.15))
    torch.testing.assert_close(out.view(3), torch.full((3,), 1 / 1.15))


def test_black_white_and_unrelated_frames_are_not_compensated(scene) -> None:
    _, _, _, model, _, _ = scene
    gen = torch.Generator().manual_seed(3)
    frames = torch.stack(
        [torch.zeros(3, H, W), torch.ones(3, H, W), quantise(torch.rand(3, H, W, generator=gen))]
    )
    out, est = match_background(frames, model)
    assert not bool(est.estimated.any())
    torch.testing.assert_close(est.gains, torch.ones(3, 3))
    torch.testing.assert_close(out, frames)


def test_errors_name_the_argument(scene) -> None:
    _, _, _, model, _, _ = scene
    with pytest.raises(ShapeError, match="images: expected shape"):
        estimate_gains(torch.zeros(3, H, W), model.rgb_mean)
    with pytest.raises(SegmentationError, match="images: expected size"):
        estimate_gains(torch.zeros(1, 3, H, W + 1), model.rgb_mean)
    with pytest.raises(SegmentationError, match="does not match the background's batch"):
        estimate_gains(torch.zeros(2, 3, H, W), model.rgb_mean.expand(3, -1, -1, -1))
