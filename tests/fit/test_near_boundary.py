"""The model contour's "near the rendered outline" test (a look-up of the pixel offsets within
the tolerance) equals the test on the whole image's exact distance transform."""

import cv2
import numpy as np
import pytest

from torchfit.fit.contour_geometry import near_boundary as _near_boundary
from torchfit.viz.raster import outer_outlines


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("tolerance", [0.5, 1.0, 2.5])
def test_the_offset_look_up_gives_the_distance_transforms_answer(seed, tolerance):
    rng = np.random.default_rng(seed)
    h, w = 120, 160
    mask = np.zeros((h, w), np.uint8)
    for _ in range(3):  # blobs, some touching the image border
        cx, cy = rng.integers(0, w), rng.integers(0, h)
        cv2.ellipse(
            mask,
            (int(cx), int(cy)),
            (int(rng.integers(5, 40)), int(rng.integers(5, 40))),
            float(rng.uniform(0, 180)),
            0,
            360,
            255,
            -1,
        )
    outlines = outer_outlines(mask)
    bpix = np.concatenate(outlines).astype(np.int64)
    boundary = np.ones((h, w), np.uint8)
    boundary[bpix[:, 1], bpix[:, 0]] = 0
    full = cv2.distanceTransform(boundary, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    ui, vi = np.meshgrid(np.arange(w), np.arange(h))
    ui, vi = ui.ravel(), vi.ravel()
    expected = full[vi, ui] <= tolerance
    near = _near_boundary(bpix, ui, vi, (w, h), tolerance)
    assert expected.any() and not expected.all()
    np.testing.assert_array_equal(near, expected)


def test_no_outline_is_near_nothing():
    ui = vi = np.arange(5)
    assert not _near_boundary(np.zeros((0, 2), np.int64), ui, vi, (10, 10), 1.0).any()
