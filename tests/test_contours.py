"""Contours, distance transforms and distance-map sampling against independent references.

References: a naive double loop of the two-pass 3-4 chamfer algorithm (below), SciPy's
``distance_transform_edt`` and OpenCV's ``findContours``.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from scipy import ndimage

from torchfit.contours import (
    chamfer_distance_transform,
    contour_mask,
    distance_map,
    euclidean_distance_transform,
    mask_to_distance_map,
    outer_contours,
    sample_distance_map,
    trace_outer_contour,
)
from torchfit.errors import ShapeError
from torchfit.io import read_mask

BIG = 10**9


def naive_chamfer_34(seeds: np.ndarray) -> np.ndarray:
    """The textbook two-pass 3-4 chamfer transform (Borgefors 1986), one pixel at a time."""
    h, w = seeds.shape
    d = np.where(seeds, 0, BIG).astype(np.int64)
    for y in range(h):
        for x in range(w):
            for dy, dx, c in ((-1, -1, 4), (-1, 0, 3), (-1, 1, 4), (0, -1, 3)):
                yy, xx = y + dy, x + dx
                if 0 <= yy < h and 0 <= xx < w:
                    d[y, x] = min(d[y, x], d[yy, xx] + c)
    for y in range(h - 1, -1, -1):
        for x in range(w - 1, -1, -1):
            for dy, dx, c in ((1, 1, 4), (1, 0, 3), (1, -1, 4), (0, 1, 3)):
                yy, xx = y + dy, x + dx
                if 0 <= yy < h and 0 <= xx < w:
                    d[y, x] = min(d[y, x], d[yy, xx] + c)
    return d


def random_blob(rng: np.random.Generator, h: int, w: int, level: float = 0.52) -> np.ndarray:
    """A smooth random single 8-connected region (uint8 0/1), possibly with holes."""
    for _ in range(100):
        field = ndimage.gaussian_filter(rng.random((h, w)), 3)
        m = (field > level).astype(np.uint8)
        n, labels = cv2.connectedComponents(m, connectivity=8)
        if n >= 2:
            sizes = np.bincount(labels.ravel())[1:]
            return (labels == 1 + int(np.argmax(sizes))).astype(np.uint8)
    raise RuntimeError("no blob")


@pytest.mark.parametrize("algorithm", ["rows", "lines", "auto"])
def test_chamfer_equals_naive_two_pass(algorithm: str) -> None:
    rng = np.random.default_rng(1)
    shapes = [(1, 1), (1, 9), (9, 1), (2, 2), (7, 13), (13, 7), (20, 31), (31, 20)]
    for h, w in shapes:
        for density in (0.003, 0.02, 0.2):
            seeds = rng.random((3, h, w)) < density
            seeds[0, rng.integers(h), rng.integers(w)] = True  # at least one seeded image
            got = chamfer_distance_transform(torch.from_numpy(seeds)[:, None], algorithm)
            assert got.shape == (3, 1, h, w) and got.dtype == torch.int32
            for b in range(3):
                if seeds[b].any():
                    np.testing.assert_array_equal(got[b, 0].numpy(), naive_chamfer_34(seeds[b]))
                else:
                    assert bool((got[b] == 2**20).all())


def test_chamfer_unknown_algorithm() -> None:
    with pytest.raises(ValueError, match="algorithm must be"):
        chamfer_distance_transform(torch.ones(1, 1, 3, 3, dtype=torch.bool), "fast")


def test_euclidean_equals_scipy_edt() -> None:
    rng = np.random.default_rng(2)
    for h, w in [(1, 1), (1, 17), (17, 1), (23, 40), (40, 23), (64, 64)]:
        for density in (0.002, 0.05, 0.5):
            seeds = rng.random((2, h, w)) < density
            seeds[0, 0, 0] = True
            got = euclidean_distance_transform(torch.from_numpy(seeds)[:, None])
            for b in range(2):
                if seeds[b].any():
                    ref = ndimage.distance_transform_edt(~seeds[b])
                    np.testing.assert_allclose(got[b, 0].numpy(), ref, rtol=1e-6, atol=1e-5)
                else:
                    assert bool(torch.isinf(got[b]).all())


def test_distance_map_units_and_empty_image() -> None:
    seeds = torch.zeros(2, 1, 9, 11, dtype=torch.bool)
    seeds[0, 0, 4, 5] = True
    cham = distance_map(seeds, "chamfer")
    eucl = distance_map(seeds, "euclidean")
    assert cham[0, 0, 4, 8].item() == pytest.approx(3.0)  # 3 axial steps
    assert cham[0, 0, 7, 8].item() == pytest.approx(4.0)  # 3 diagonal steps: 12 / 3
    assert eucl[0, 0, 7, 8].item() == pytest.approx(np.sqrt(18.0))
    assert bool(torch.isinf(cham[1]).all()) and bool(torch.isinf(eucl[1]).all())
    with pytest.raises(ValueError, match="method must be"):
        distance_map(seeds, "manhattan")


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


def test_real_silhouettes_contour_and_distance(shared_data) -> None:
    """CDnet person masks: contour equals OpenCV's, chamfer/3 stays within the 3-4 metric's
    bounds of the exact Euclidean map (0.94 .. 1.06), and a crop matches the naive loop."""
    folder = shared_data / "cdnet2014-shadow-groundtruth" / "peopleInShade200"
    files = sorted(folder.glob("gt*.png"))[::40]
    masks = []
    for f in files:
        person = (read_mask(f) == 255).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(person, connectivity=8)
        if n < 2:
            continue
        biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        masks.append((labels == biggest).astype(np.uint8))
    assert len(masks) >= 3
    t = torch.from_numpy(np.stack(masks).astype(bool))[:, None]
    for m, pts in zip(masks, outer_contours(t), strict=True):
        ref, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        np.testing.assert_array_equal(pts.numpy(), ref[0][:, 0, :])
    cham = mask_to_distance_map(t, "chamfer")
    eucl = mask_to_distance_map(t, "euclidean")
    seeds = contour_mask(t)
    for b in range(len(masks)):
        ref = ndimage.distance_transform_edt(~seeds[b, 0].numpy())
        np.testing.assert_allclose(eucl[b, 0].numpy(), ref, rtol=1e-6, atol=1e-5)
        c, e = cham[b, 0].numpy(), eucl[b, 0].numpy()
        assert np.all(c >= 0.942 * e - 1e-4) and np.all(c <= 1.055 * e + 1e-4)
    ys, xs = np.nonzero(seeds[0, 0].numpy())
    y0, x0 = max(int(ys.mean()) - 20, 0), max(int(xs.mean()) - 20, 0)
    crop = seeds[:1, :, y0 : y0 + 40, x0 : x0 + 40]
    np.testing.assert_array_equal(
        chamfer_distance_transform(crop)[0, 0].numpy(), naive_chamfer_34(crop[0, 0].numpy())
    )


def test_sample_distance_map_values_and_convention() -> None:
    gen = torch.Generator().manual_seed(0)
    dist = torch.rand(2, 1, 6, 9, generator=gen, dtype=torch.float64)
    # Integer points hit the pixel centres: (u, v) -> dist[..., v, u].
    pts = torch.tensor([[[0.0, 0.0], [8.0, 5.0], [3.0, 2.0]], [[1.0, 4.0], [0.0, 5.0], [8.0, 0.0]]])
    got = sample_distance_map(dist, pts.double())
    ref = torch.stack([dist[b, 0, pts[b, :, 1].long(), pts[b, :, 0].long()] for b in range(2)])
    torch.testing.assert_close(got, ref)
    # A sub-pixel point is the bilinear blend of its four neighbours.
    u, v = 2.25, 3.6
    d = dist[0, 0]
    manual = (
        d[3, 2] * 0.75 * 0.4 + d[3, 3] * 0.25 * 0.4 + d[4, 2] * 0.75 * 0.6 + d[4, 3] * 0.25 * 0.6
    )
    one = sample_distance_map(dist[:1], torch.tensor([[[u, v]]], dtype=torch.float64))
    torch.testing.assert_close(one[0, 0], manual)
    # Outside points are clamped to the border.
    far = sample_distance_map(dist[:1], torch.tensor([[[-5.0, 2.0], [20.0, 9.0]]]).double())
    torch.testing.assert_close(far[0], torch.stack([d[2, 0], d[5, 8]]))


def test_sample_distance_map_gradient_matches_finite_differences() -> None:
    gen = torch.Generator().manual_seed(1)
    dist = torch.rand(2, 1, 8, 10, generator=gen, dtype=torch.float64) * 5
    pts = torch.rand(2, 7, 2, generator=gen, dtype=torch.float64) * torch.tensor([8.6, 6.6])
    pts = (pts + 0.2).requires_grad_(True)  # away from integer grid lines (kinks)
    assert torch.autograd.gradcheck(lambda p: sample_distance_map(dist, p), (pts,))


def test_sample_distance_map_errors() -> None:
    dist = torch.zeros(2, 1, 5, 5)
    with pytest.raises(ShapeError, match=r"points: expected shape \(2, N, 2\)"):
        sample_distance_map(dist, torch.zeros(1, 3, 2))
    with pytest.raises(ShapeError, match="points: expected dtype"):
        sample_distance_map(dist, torch.zeros(2, 3, 2, dtype=torch.float64))
    with pytest.raises(ShapeError, match=r"dist: expected shape \(B, 1, H, W\)"):
        sample_distance_map(torch.zeros(2, 5, 5), torch.zeros(2, 3, 2))
