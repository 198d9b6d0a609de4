"""Ordered outer contours against OpenCV's ``findContours``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from image_testing import random_blob
from scipy import ndimage

from torchfit.errors import ShapeError
from torchfit.image import (
    contour_mask,
    contour_normals,
    outer_contours,
    trace_outer_contour,
)


def test_trace_matches_opencv_find_contours() -> None:
    rng = np.random.default_rng(3)
    for i in range(40):
        h, w = (30, 45) if i % 2 else (41, 29)
        m = random_blob(rng, h, w, level=0.5 + 0.01 * (i % 5))
        ref, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        assert len(ref) == 1
        got = trace_outer_contour(m)
        np.testing.assert_array_equal(got.numpy(), ref[0][:, 0, :])


@pytest.mark.parametrize(
    "name",
    ["single", "hline", "vline", "diagonal", "spur", "ring", "full", "corner"],
)
def test_trace_special_shapes_match_opencv(name: str) -> None:
    m = np.zeros((12, 14), np.uint8)
    if name == "single":
        m[5, 6] = 1
    elif name == "hline":
        m[4, 2:10] = 1
    elif name == "vline":
        m[1:9, 3] = 1
    elif name == "diagonal":
        for k in range(7):
            m[2 + k, 3 + k] = 1
    elif name == "spur":
        m[3:8, 3:8] = 1
        m[5, 8:12] = 1
    elif name == "ring":
        m[2:10, 2:12] = 1
        m[4:8, 5:9] = 0
    elif name == "full":
        m[:] = 1
    elif name == "corner":
        m[0:4, 0:5] = 1
        m[4:8, 5:9] = 1  # touches only diagonally: one 8-connected region
    ref, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    np.testing.assert_array_equal(trace_outer_contour(m).numpy(), ref[0][:, 0, :])


def test_trace_empty_and_bad_shape() -> None:
    assert trace_outer_contour(np.zeros((5, 5), np.uint8)).shape == (0, 2)
    with pytest.raises(ShapeError, match=r"mask: expected shape \(H, W\)"):
        trace_outer_contour(np.zeros((1, 5, 5)))
    with pytest.raises(ShapeError, match="masks: expected shape"):
        outer_contours(torch.zeros(5, 5, dtype=torch.bool))
    with pytest.raises(ShapeError, match="expected a bool mask"):
        contour_mask(torch.zeros(1, 1, 5, 5))


def test_contour_mask_is_the_4_adjacent_border_of_a_hole_free_region() -> None:
    """Independent check: the outer border is every pixel with a 4-neighbour outside."""
    rng = np.random.default_rng(4)
    cross = ndimage.generate_binary_structure(2, 1)
    masks = []
    for _ in range(6):
        masks.append(ndimage.binary_fill_holes(random_blob(rng, 40, 50)))
    t = torch.from_numpy(np.stack(masks))[:, None]
    got = contour_mask(t)[:, 0].numpy()
    for m, g in zip(masks, got, strict=True):
        ref = m & ~ndimage.binary_erosion(m, cross, border_value=0)
        np.testing.assert_array_equal(g, ref)


def test_contour_normals_point_out_of_a_disk_and_a_rectangle() -> None:
    yy, xx = np.mgrid[:60, :80]
    disk = (xx - 40) ** 2 + (yy - 30) ** 2 < 20**2
    c = trace_outer_contour(disk)
    n = contour_normals(c)
    radial = c.float() - torch.tensor([40.0, 30.0])
    radial = radial / radial.norm(dim=1, keepdim=True)
    assert n.norm(dim=1).sub(1).abs().max() < 1e-6
    assert (n * radial).sum(1).min() > 0.95
    rect = np.zeros((40, 50), bool)
    rect[10:30, 5:45] = True
    c = trace_outer_contour(rect)
    n = contour_normals(c)
    # away from the corners, the sides' normals are the axes
    sides = {"top": (0, -1), "bottom": (0, 1), "left": (-1, 0), "right": (1, 0)}
    for side, (u, v) in sides.items():
        if side in ("top", "bottom"):
            at = (c[:, 1] == (10 if side == "top" else 29)) & (c[:, 0] > 10) & (c[:, 0] < 40)
        else:
            at = (c[:, 0] == (5 if side == "left" else 44)) & (c[:, 1] > 14) & (c[:, 1] < 26)
        assert at.sum() > 5
        assert torch.allclose(n[at], torch.tensor([[float(u), float(v)]]).expand(int(at.sum()), 2))


def test_contour_normals_of_a_too_short_contour_are_zero() -> None:
    assert contour_normals(torch.tensor([[3, 4], [4, 4]])).abs().sum() == 0
    with pytest.raises(ShapeError):
        contour_normals(torch.zeros(5, 3))
