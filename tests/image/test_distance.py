"""Distance transforms and distance-map sampling against independent references.

References: a naive double loop of the two-pass 3-4 chamfer algorithm, SciPy's
``distance_transform_edt`` and hand-computed bilinear blends.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from image_testing import naive_chamfer_34
from scipy import ndimage

from torchfit.errors import ShapeError
from torchfit.image import (
    chamfer_distance_transform,
    contour_mask,
    distance_map,
    euclidean_distance_transform,
    mask_to_distance_map,
    outer_contours,
    sample_distance_map,
)
from torchfit.io import read_mask


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
    with pytest.raises(ShapeError, match="expected floating tensors"):
        sample_distance_map(dist, torch.zeros(2, 3, 2, dtype=torch.int64))
    with pytest.raises(ShapeError, match=r"dist: expected shape \(B, 1, H, W\)"):
        sample_distance_map(torch.zeros(2, 5, 5), torch.zeros(2, 3, 2))


def _old_sample_rows(dmap: torch.Tensor, rows: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """The fit's former per-row sampler (SilhouetteFit._sample_rows), verbatim: (B, H, W)."""
    h, w = dmap.shape[-2:]
    u = points[..., 0].clamp(0, w - 1)
    v = points[..., 1].clamp(0, h - 1)
    u0 = u.detach().floor().clamp(max=w - 2)
    v0 = v.detach().floor().clamp(max=h - 2)
    fu, fv = u - u0, v - v0
    u0, v0 = u0.long(), v0.long()
    r = rows[:, None].expand_as(u0)
    d00, d01 = dmap[r, v0, u0], dmap[r, v0, u0 + 1]
    d10, d11 = dmap[r, v0 + 1, u0], dmap[r, v0 + 1, u0 + 1]
    return (d00 * (1 - fu) + d01 * fu) * (1 - fv) + (d10 * (1 - fu) + d11 * fu) * fv


def _old_grid_sample(dist: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """The former sample_distance_map (grid_sample, border padding)."""
    h, w = dist.shape[-2:]
    scale = points.new_tensor([2.0 / (w - 1), 2.0 / (h - 1)])
    grid = (points * scale - 1.0).unsqueeze(1)
    out = torch.nn.functional.grid_sample(
        dist, grid, mode="bilinear", padding_mode="border", align_corners=True
    )
    return out[:, 0, 0, :]


def test_sample_distance_map_rows_equals_the_former_fit_sampler_bitwise() -> None:
    import torch.autograd.forward_ad as fwad

    gen = torch.Generator().manual_seed(3)
    dmap = torch.rand(3, 12, 17, generator=gen, dtype=torch.float64) * 9
    rows = torch.tensor([2, 0, 0, 1, 2])
    points = torch.rand(5, 40, 2, generator=gen, dtype=torch.float64) * 24 - 4
    points[0, :5] = torch.tensor([[0.0, 0.0], [16.0, 11.0], [3.0, 7.0], [16.0, 0.0], [2.5, 11.0]])
    got = sample_distance_map(dmap.unsqueeze(1), points, rows)
    assert torch.equal(got, _old_sample_rows(dmap, rows, points))
    # reverse mode
    p1 = points.clone().requires_grad_(True)
    p2 = points.clone().requires_grad_(True)
    sample_distance_map(dmap.unsqueeze(1), p1, rows).square().sum().backward()
    _old_sample_rows(dmap, rows, p2).square().sum().backward()
    assert torch.equal(p1.grad, p2.grad)
    # forward mode (the fit's Jacobian pushes dual pixels through the sampler)
    tangent = torch.randn(points.shape, generator=gen, dtype=torch.float64)
    with fwad.dual_level():
        a = fwad.unpack_dual(
            sample_distance_map(dmap.unsqueeze(1), fwad.make_dual(points, tangent), rows)
        )
        b = fwad.unpack_dual(_old_sample_rows(dmap, rows, fwad.make_dual(points, tangent)))
        assert torch.equal(a.primal, b.primal) and torch.equal(a.tangent, b.tangent)
    # one map per row without ``rows`` agrees with the former grid_sample version to rounding
    batch = points[:3]
    torch.testing.assert_close(
        sample_distance_map(dmap.unsqueeze(1), batch),
        _old_grid_sample(dmap.unsqueeze(1), batch),
        rtol=0,
        atol=1e-12,
    )
    with pytest.raises(ShapeError, match=r"rows: expected shape \(5\)"):
        sample_distance_map(dmap.unsqueeze(1), points, rows[:4])


def test_a_float32_map_samples_as_its_float64_copy_bitwise() -> None:
    """The person's maps are kept in float32: read at float64 points, every value and
    derivative is that of the float64 copy (the corners are cast before they are blended)."""
    gen = torch.Generator().manual_seed(4)
    whole = torch.randint(0, 300, (3, 1, 12, 17), generator=gen).to(torch.float32) / 3.0
    rows = torch.tensor([2, 0, 1, 1])
    points = torch.rand(4, 30, 2, generator=gen, dtype=torch.float64) * 22 - 3
    p32 = points.clone().requires_grad_(True)
    p64 = points.clone().requires_grad_(True)
    a = sample_distance_map(whole, p32, rows)
    b = sample_distance_map(whole.double(), p64, rows)
    assert a.dtype == torch.float64
    assert torch.equal(a, b)
    a.square().sum().backward()
    b.square().sum().backward()
    assert torch.equal(p32.grad, p64.grad)
