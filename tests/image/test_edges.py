"""The outline's mixed pixels: a pixel the person covers less than half is background.

The scenes are rendered by area coverage (each pixel the mean of 8 x 8 sub-pixels), so the
true coverage of every pixel is known; the true silhouette is the pixels covered at least half.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from image_testing import quantise

from torchfit.errors import ConfigError
from torchfit.image import SegmentationOptions, fit_background, refine_edges, segment

H, W, S = 64, 80, 8  # image size and sub-pixels per pixel side


def _coverage() -> torch.Tensor:
    """(H, W) share of each pixel inside a tilted body with round head and an arm."""
    yy, xx = torch.meshgrid(
        (torch.arange(H * S) + 0.5) / S, (torch.arange(W * S) + 0.5) / S, indexing="ij"
    )
    body = ((xx - 40) / 9.3) ** 2 + ((yy - 38) / 20.7) ** 2 <= 1
    head = (xx - 41.2) ** 2 + (yy - 12.4) ** 2 <= 6.6**2
    arm = ((yy - 0.45 * xx - 10.3).abs() <= 2.6) & (xx > 45) & (xx < 70.5)
    inside = (body | head | arm).float()
    return torch.nn.functional.avg_pool2d(inside[None, None], S)[0, 0]


def _scene(person_rgb, seed: int = 0, sigma: float = 0.008, texture: float = 0.1):
    gen = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    tone = 1 + texture * torch.sin(xx * 0.4 + yy * 0.2)
    wall = torch.tensor([0.55, 0.5, 0.45]).view(3, 1, 1) * tone
    cover = _coverage()
    image = cover * torch.tensor(person_rgb).view(3, 1, 1) + (1 - cover) * wall
    frames = quantise((wall + sigma * torch.randn(6, 3, H, W, generator=gen)).clamp(0, 1))
    image = quantise((image + sigma * torch.randn(3, H, W, generator=gen)).clamp(0, 1))[None]
    return frames, image, cover


def _f(mask: torch.Tensor, truth: torch.Tensor) -> tuple[float, float, float]:
    tp = int((mask & truth).sum())
    p, r = tp / max(int(mask.sum()), 1), tp / max(int(truth.sum()), 1)
    return p, r, 2 * p * r / max(p + r, 1e-9)


@pytest.mark.parametrize(
    "person, separable",
    [((0.15, 0.2, 0.5), True), ((0.7, 0.2, 0.15), True), ((0.9, 0.85, 0.8), False)],
)
def test_outline_pixels_covered_less_than_half_become_background(person, separable) -> None:
    frames, image, cover = _scene(person)
    truth = cover >= 0.5
    model = fit_background(frames)
    before = segment(image, model, SegmentationOptions(edge_width=0)).masks[0, 0]
    after = segment(image, model, SegmentationOptions(edge_width=2)).masks[0, 0]
    if not separable:  # a light grey person before a darker grey wall: a shade of each other
        assert torch.equal(before, after)
        return
    p0, r0, f0 = _f(before, truth)
    p1, r1, f1 = _f(after, truth)
    assert p1 > p0 and f1 > f0, (p0, r0, f0, p1, r1, f1)
    assert f1 > 0.97 and r1 > 0.97
    # what it drops was mostly background, and nothing well inside the person
    dropped = before & ~after
    assert int(dropped.sum()) > 0
    assert float(cover[dropped].mean()) < 0.5
    assert not bool((dropped & (cover > 0.9)).any())
    # nothing added, one region
    assert not bool((after & ~before).any())

    assert cv2.connectedComponents(after.numpy().astype(np.uint8), connectivity=8)[0] == 2


def test_nothing_is_dropped_where_person_and_background_are_alike_or_width_is_zero() -> None:
    # a person's colour within the separation (6 noise deviations) of a flat wall's
    frames, image, cover = _scene((0.565, 0.51, 0.46), texture=0.0)
    model = fit_background(frames)
    masks = (cover > 0.05)[None, None]
    assert torch.equal(refine_edges(image, model, masks, 2), masks)
    frames, image, cover = _scene((0.15, 0.2, 0.5))
    model = fit_background(frames)
    assert torch.equal(refine_edges(image, model, masks, 0), masks)
    empty = torch.zeros_like(masks)
    assert torch.equal(refine_edges(image, model, empty, 2), empty)


def test_a_shaded_outline_stays_person_and_the_test_is_on_by_default() -> None:
    frames, image, cover = _scene((0.15, 0.2, 0.5))
    model = fit_background(frames)
    truth = (cover >= 0.5)[None, None]
    # the person's outline shaded to 40 % of its colour (turning away from the light): darker,
    # not a mix with the wall, so it stays
    rim = (
        truth
        & ~torch.from_numpy(
            cv2.erode(truth[0, 0].numpy().astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        )[None, None]
    )
    person = torch.tensor([0.15, 0.2, 0.5]).view(1, 3, 1, 1)
    solid = torch.where(truth, person, model.rgb_mean)
    shaded = quantise(torch.where(rim, 0.4 * person, solid))
    assert torch.equal(refine_edges(shaded, model, truth, 2), truth)
    assert SegmentationOptions().edge_width == 2
    on = segment(image, model, SegmentationOptions(edge_width=2)).masks
    assert torch.equal(segment(image, model).masks, on)


def test_outline_test_checks_its_arguments() -> None:
    frames, image, cover = _scene((0.15, 0.2, 0.5))
    model = fit_background(frames)
    masks = (cover > 0.5)[None, None]
    with pytest.raises(ValueError, match="width and separation"):
        refine_edges(image, model, masks, -1)
    with pytest.raises(ConfigError, match="segmentation.edge_width"):
        segment(image, model, SegmentationOptions(edge_width=-2))
    np.testing.assert_array_equal(refine_edges(image, model, masks, 1).shape, masks.shape)
