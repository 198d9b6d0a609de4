"""Opening and closing against kornia; hole filling and largest region against former copies."""

from __future__ import annotations

import cv2
import kornia
import numpy as np
import pytest
import torch
from scipy import ndimage

from torchfit.errors import ShapeError
from torchfit.image import clean_mask, fill_holes, largest_component


@pytest.mark.parametrize("k", [3, 5, 7])
def test_clean_mask_morphology_equals_kornia(k: int) -> None:
    gen = torch.Generator().manual_seed(k)
    masks = torch.rand(2, 1, 23, 31, generator=gen) < 0.55
    ones = torch.ones(k, k)
    opened = kornia.morphology.opening(masks.float(), ones) > 0.5
    got = clean_mask(masks, open_kernel=k, close_kernel=1, fill_holes=False, largest_region=False)
    assert torch.equal(got, opened)
    closed = kornia.morphology.closing(masks.float(), ones) > 0.5
    got = clean_mask(masks, open_kernel=1, close_kernel=k, fill_holes=False, largest_region=False)
    assert torch.equal(got, closed)
    with pytest.raises(ValueError, match="close_kernel must be odd"):
        clean_mask(masks, 3, 4)
    with pytest.raises(ShapeError, match="expected a bool tensor"):
        clean_mask(masks.float())


# The former copies, verbatim, that torchfit.image.morphology replaces: segmentation's
# _largest_region and _fill_holes, baseline's largest-blob selection and parts.decompose's
# fill_holes. The merged functions must give the same pixels on every mask.
def _old_largest_region(mask: np.ndarray) -> np.ndarray:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return np.zeros_like(mask)
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return (labels == biggest).astype(np.uint8)


def _old_baseline_largest(mask: np.ndarray) -> np.ndarray:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return np.zeros(mask.shape, dtype=bool)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == largest


def _old_fill_holes(mask: np.ndarray, max_fraction: float | None) -> np.ndarray:
    padded = np.pad(mask, 1)
    flood = padded.copy()
    cv2.floodFill(flood, None, (0, 0), 1)
    holes = (1 - flood[1:-1, 1:-1]).astype(np.uint8)
    if max_fraction is None:
        return mask | holes
    limit = max_fraction * (int(mask.sum()) + int(holes.sum()))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(holes, connectivity=4)
    small = np.zeros(n, dtype=np.uint8)
    small[1:] = stats[1:, cv2.CC_STAT_AREA] <= limit
    return mask | small[labels]


def _old_parts_fill_holes(mask: np.ndarray) -> np.ndarray:
    h, w = mask.shape
    pad = np.zeros((h + 2, w + 2), dtype=np.uint8)
    pad[1:-1, 1:-1] = mask
    flood = pad.copy()
    cv2.floodFill(flood, np.zeros((h + 4, w + 4), np.uint8), (0, 0), 2)
    return flood[1:-1, 1:-1] != 2


def _random_masks(n: int):
    rng = np.random.default_rng(7)
    for i in range(n):
        h, w = int(rng.integers(1, 40)), int(rng.integers(1, 40))
        kind = i % 4
        if kind == 0:  # speckle of any density
            yield (rng.random((h, w)) < rng.random()).astype(np.uint8)
        elif kind == 1:  # smooth blobs with holes, several regions
            field = ndimage.gaussian_filter(rng.random((h, w)), 1.5)
            yield (field > np.quantile(field, rng.uniform(0.2, 0.8))).astype(np.uint8)
        elif kind == 2:  # rings: holes touching nothing but the region
            m = np.zeros((h, w), np.uint8)
            for _ in range(3):
                y, x = rng.integers(0, h), rng.integers(0, w)
                r = int(rng.integers(2, 8))
                cv2.circle(m, (int(x), int(y)), r, 1, thickness=int(rng.integers(1, 3)))
            yield m
        else:  # empty or full
            yield np.full((h, w), i % 8 == 3, np.uint8)


def test_largest_component_equals_its_former_copies() -> None:
    for m in _random_masks(400):
        got = largest_component(m)
        assert got.dtype == bool
        np.testing.assert_array_equal(got, _old_largest_region(m).astype(bool))
        np.testing.assert_array_equal(got, _old_baseline_largest(m))
        np.testing.assert_array_equal(largest_component(m.astype(bool)), got)


def test_fill_holes_equals_its_former_copies() -> None:
    for m in _random_masks(400):
        got = fill_holes(m)
        assert got.dtype == bool
        np.testing.assert_array_equal(got, _old_fill_holes(m, None).astype(bool))
        np.testing.assert_array_equal(got, _old_parts_fill_holes(m.astype(bool)))
        np.testing.assert_array_equal(fill_holes(m.astype(bool)), got)
        for frac in (0.0, 0.01, 0.1, 1.0):
            np.testing.assert_array_equal(
                fill_holes(m, frac), _old_fill_holes(m, frac).astype(bool)
            )
