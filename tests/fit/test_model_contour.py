"""Tests of torchfit.fit.model_contour: edge samples, the contour choice, point-to-edge distances.

References: hand-enumerated edges of tiny meshes (two triangles, a tetrahedron); the outline
of the rendered mask computed here with numpy (mask pixels with a 4-neighbour outside) and a
brute-force nearest-sample search; a naive per-point point-to-segment loop in plain Python
(projection parameter clamped to the sample's piece ``[t0 - half, t0 + half]``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchfit.errors import ShapeError
from torchfit.fit.contour_geometry import outward_normals
from torchfit.fit.model_contour import (
    ContourSelection,
    EdgeSampler,
    contour_endpoints,
    point_to_edge_distance,
    select_contour,
)

SQUARE_FACES = torch.tensor([[0, 1, 2], [0, 2, 3]])
TETRA_FACES = torch.tensor([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])


def _square(u0: float, v0: float, u1: float, v1: float) -> torch.Tensor:
    return torch.tensor([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], dtype=torch.float64)


EPS = 1e-6  # point_to_edge_distance returns sqrt(d^2 + EPS^2) - EPS (about d - 1e-6)


def _smooth(d: float) -> float:
    return math.sqrt(d * d + EPS * EPS) - EPS


def _naive_piece_distance(x, a, b, t0, half) -> float:
    """Distance from point x to {a + t (b - a) : t in [t0 - half, t0 + half]} (plain Python)."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    ll = dx * dx + dy * dy
    t = ((x[0] - a[0]) * dx + (x[1] - a[1]) * dy) / ll if ll > 0 else 0.0
    t = min(max(t, t0 - half), t0 + half)
    px, py = a[0] + t * dx, a[1] + t * dy
    return math.hypot(x[0] - px, x[1] - py)


def _outline_pixels(mask: np.ndarray) -> np.ndarray:
    """(N, 2) (u, v) of mask pixels with a 4-neighbour outside the mask (or the image)."""
    m = np.pad(mask > 0, 1)
    inner = m[1:-1, 1:-1] & m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]
    v, u = np.nonzero((mask > 0) & ~inner)
    return np.stack([u, v], 1).astype(np.float64)


# --------------------------------------------------------------------------------------------
# EdgeSampler


def test_edge_sampler_two_triangles():
    s = EdgeSampler(SQUARE_FACES, samples_per_edge=4)
    assert s.edges.tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]]
    assert s.num_samples == 5 * 4
    # the diagonal (0, 2) has both faces (in either order), the four sides border one face only
    ef = s.edge_faces.tolist()
    assert sorted(ef[1]) == [0, 1]
    assert [ef[i] for i in (0, 2, 3, 4)] == [[0, -1], [1, -1], [0, -1], [1, -1]]
    idx = torch.arange(s.num_samples)
    a, b = s.endpoints(idx)
    assert a.tolist() == [e[0] for e in s.edges.tolist() for _ in range(4)]
    assert b.tolist() == [e[1] for e in s.edges.tolist() for _ in range(4)]
    torch.testing.assert_close(
        s.fraction(idx), torch.tensor([0.125, 0.375, 0.625, 0.875] * 5, dtype=torch.float64)
    )
    pix = _square(0.0, 0.0, 8.0, 4.0)[None]
    pts = s.all_points(pix)
    assert pts.shape == (1, 20, 2)
    # edge (1, 2): from (8, 0) to (8, 4) -> v = 4 t
    torch.testing.assert_close(
        pts[0, 12:16], torch.tensor([[8.0, 0.5], [8.0, 1.5], [8.0, 2.5], [8.0, 3.5]]).double()
    )
    # every sample equals the lerp of its endpoints at its fraction
    t = s.fraction(idx)[:, None]
    torch.testing.assert_close(pts[0], pix[0, a] * (1 - t) + pix[0, b] * t)


def test_edge_sampler_tetrahedron_and_bad_k():
    s = EdgeSampler(TETRA_FACES, samples_per_edge=1)
    assert s.edges.shape == (6, 2) and s.num_samples == 6
    assert (s.edge_faces >= 0).all()  # closed mesh: every edge has two faces
    for e, (f0, f1) in zip(s.edges.tolist(), s.edge_faces.tolist(), strict=True):
        assert f0 != f1
        for f in (f0, f1):
            assert set(e) <= set(TETRA_FACES[f].tolist())
    torch.testing.assert_close(s.fraction(torch.tensor([0, 5])), torch.tensor([0.5, 0.5]).double())
    with pytest.raises(ShapeError, match="samples_per_edge: expected >= 1, got 0"):
        EdgeSampler(TETRA_FACES, samples_per_edge=0)


def test_silhouette_edges_of_a_projected_tetrahedron():
    # vertex 3 projects inside the triangle 0-1-2: the outer edges separate the base from a
    # side face (opposite facing), the inner edges join two side faces (same facing)
    s = EdgeSampler(TETRA_FACES, samples_per_edge=1)
    pix = np.array([[10.0, 10.0], [50.0, 10.0], [30.0, 45.0], [30.0, 22.0]])
    sil = s.silhouette_edges(pix)
    outer = {(0, 1), (0, 2), (1, 2)}
    assert [tuple(e) in outer for e in s.edges.tolist()] == sil.tolist()
    # the flat square: only the 4 border edges, not the diagonal
    sq = EdgeSampler(SQUARE_FACES, 2)
    assert sq.silhouette_edges(_square(0, 0, 5, 5).numpy()).tolist() == [1, 0, 1, 1, 1]


# --------------------------------------------------------------------------------------------
# select_contour / contour_endpoints


def test_select_contour_on_a_square_lies_on_the_rendered_outline():
    k = 4
    s = EdgeSampler(SQUARE_FACES, samples_per_edge=k)
    pix = _square(10.0, 12.0, 50.0, 40.0)[None]
    g = np.random.default_rng(0)
    person = torch.from_numpy(g.uniform(0, 63, size=(1, 30, 2)))
    valid = torch.ones(1, 30, dtype=torch.bool)
    valid[0, -5:] = False
    sel = select_contour(s, pix, person, valid, (64, 64), tolerance=1.0)
    assert isinstance(sel, ContourSelection)
    chosen = sel.samples[0][sel.sample_valid[0]]
    # every sample of the 4 sides, none of the diagonal (edge 1)
    expected = [i for i in range(s.num_samples) if i // k != 1]
    assert sorted(chosen.tolist()) == expected
    # the chosen samples lie on the outline of the rendered mask
    mask = sel.mask(0)
    assert mask.shape == (64, 64) and mask[26, 30] == 255 and mask[5, 5] == 0
    outline = _outline_pixels(mask)
    pts = s.all_points(pix)[0, chosen].numpy()
    d = np.linalg.norm(pts[:, None] - outline[None], axis=-1).min(1)
    assert d.max() <= 1.0
    # diagonal samples are further from the outline than the tolerance (nearest: 3.5 px)
    diag = s.all_points(pix)[0, k : 2 * k].numpy()
    assert np.linalg.norm(diag[:, None] - outline[None], axis=-1).min() == pytest.approx(3.5)
    # nearest: brute-force nearest chosen sample for each valid person pixel, 0 on padding
    all_pts = s.all_points(pix)[0, sel.samples[0]].numpy()
    for c in range(30):
        if valid[0, c]:
            dist = np.linalg.norm(all_pts - person[0, c].numpy(), axis=1)
            dist[~sel.sample_valid[0].numpy()] = np.inf
            assert dist[sel.nearest[0, c]] == pytest.approx(dist.min())
        else:
            assert sel.nearest[0, c] == 0


def test_select_contour_batch_padding_off_image_and_empty():
    s = EdgeSampler(SQUARE_FACES, samples_per_edge=2)
    pix = torch.stack(
        [
            _square(10.0, 10.0, 30.0, 30.0),  # fully in view: 4 sides x 2 samples
            _square(20.0, -30.0, 30.0, 20.0),  # top side and half of each side out of view
            _square(100.0, 100.0, 120.0, 120.0),  # entirely out of view
        ]
    )
    person = torch.full((3, 4, 2), 15.0, dtype=torch.float64)
    valid = torch.ones(3, 4, dtype=torch.bool)
    sel = select_contour(s, pix, person, valid, (40, 40))
    counts = sel.sample_valid.sum(1).tolist()
    assert sel.samples.shape == (3, 8) and counts == [8, 4, 0]
    # padding is index 0 and invalid
    assert (sel.samples[1, 4:] == 0).all() and (sel.samples[2] == 0).all()
    # row 1: samples at v = -17.5 (top side, upper halves of the sides) are out of view; the
    # bottom side's two and the lower sample of each side (v = 7.5) are kept
    pts = s.all_points(pix)[1, sel.samples[1, :4]]
    assert sorted(pts.tolist()) == [[20.0, 7.5], [22.5, 20.0], [27.5, 20.0], [30.0, 7.5]]
    assert (sel.nearest[2] == 0).all()  # nothing to point to
    # repeat_interleave: row b*r + i is row b
    rep = sel.repeat_interleave(2)
    assert rep.samples.shape == (6, 8) and len(rep.silhouettes) == 6
    for r in range(6):
        assert torch.equal(rep.samples[r], sel.samples[r // 2])
        assert torch.equal(rep.sample_valid[r], sel.sample_valid[r // 2])
        assert torch.equal(rep.nearest[r], sel.nearest[r // 2])
        assert rep.silhouettes[r] is sel.silhouettes[r // 2]


def test_contour_endpoints_resolve_the_selection():
    k = 3
    s = EdgeSampler(TETRA_FACES, samples_per_edge=k)
    pix = torch.tensor([[[10.0, 10.0], [50.0, 10.0], [30.0, 45.0], [30.0, 22.0]]]).double()
    g = np.random.default_rng(1)
    person = torch.from_numpy(g.uniform(5, 55, size=(1, 12, 2)))
    valid = torch.ones(1, 12, dtype=torch.bool)
    sel = select_contour(s, pix, person, valid, (64, 64))
    ends = contour_endpoints(s, sel)
    n = int(sel.sample_valid.sum())
    assert n == 3 * k  # only the three outer edges
    edges = s.edges.tolist()
    for j in range(n):
        i = int(sel.samples[0, j])
        assert [int(ends.model_a[0, j]), int(ends.model_b[0, j])] == edges[i // k]
        assert float(ends.model_t[0, j]) == pytest.approx((i % k + 0.5) / k)
    all_pts = s.all_points(pix)[0]
    for c in range(12):
        i = int(sel.samples[0, sel.nearest[0, c]])
        a, b, t = ends.person_a[0, c], ends.person_b[0, c], ends.person_t[0, c]
        torch.testing.assert_close(pix[0, a] * (1 - t) + pix[0, b] * t, all_pts[i])
    assert ends.vertices().tolist() == [0, 1, 2]  # the inner vertex 3 is not on the contour


# --------------------------------------------------------------------------------------------
# point_to_edge_distance


def test_point_to_edge_distance_hand_computed():
    a = torch.tensor([0.0, 0.0], dtype=torch.float64).expand(4, 2)
    b = torch.tensor([4.0, 0.0], dtype=torch.float64).expand(4, 2)
    x = torch.tensor([[2.0, 3.0], [-3.0, 4.0], [1.0, 0.0], [3.5, 1.0]], dtype=torch.float64)
    t0 = torch.tensor([0.5, 0.125, 0.875, 0.125], dtype=torch.float64)
    d = point_to_edge_distance(x, a, b, t0, 0.125)
    # piece [0.375, 0.625] = u in [1.5, 2.5]: above it -> 3
    # piece [0, 0.25] = u in [0, 1]: from (-3, 4) to (0, 0) -> 5
    # piece [0.75, 1] = u in [3, 4]: from (1, 0) to (3, 0) -> 2 (not 0: other pieces don't count)
    # piece [0, 0.25]: from (3.5, 1) to (1, 0) -> sqrt(6.25 + 1)
    expected = torch.tensor(
        [_smooth(v) for v in (3.0, 5.0, 2.0, math.sqrt(7.25))], dtype=torch.float64
    )
    torch.testing.assert_close(d, expected, atol=1e-9, rtol=0)


def test_point_to_edge_distance_matches_naive_loop_on_random_data():
    g = np.random.default_rng(2)
    n_pts, k = 200, 4
    half = 0.5 / k
    x = g.uniform(0, 100, size=(2, n_pts, 2))
    a = g.uniform(0, 100, size=(2, n_pts, 2))
    b = a + g.normal(0, 15, size=(2, n_pts, 2))
    t0 = (g.integers(0, k, size=(2, n_pts)) + 0.5) / k
    got = point_to_edge_distance(*(torch.from_numpy(v) for v in (x, a, b, t0)), half).numpy()
    for i in range(2):
        for j in range(n_pts):
            ref = _naive_piece_distance(x[i, j], a[i, j], b[i, j], t0[i, j], half)
            assert got[i, j] == pytest.approx(_smooth(ref), abs=1e-9)


def test_point_to_edge_distance_min_over_pieces_is_the_segment_distance():
    # the K pieces of an edge tile it, so the min over the pieces (and over candidate edges)
    # is the ordinary point-to-segment distance
    g = np.random.default_rng(3)
    k, n_edges, n_pts = 4, 5, 60
    half = 0.5 / k
    a = g.uniform(0, 50, size=(n_edges, 2))
    b = g.uniform(0, 50, size=(n_edges, 2))
    x = g.uniform(-10, 60, size=(n_pts, 2))
    t0 = (np.arange(k) + 0.5) / k
    # broadcast to (P, E, K)
    xx = np.broadcast_to(x[:, None, None], (n_pts, n_edges, k, 2))
    aa = np.broadcast_to(a[None, :, None], (n_pts, n_edges, k, 2))
    bb = np.broadcast_to(b[None, :, None], (n_pts, n_edges, k, 2))
    tt = np.broadcast_to(t0[None, None], (n_pts, n_edges, k))
    d = point_to_edge_distance(
        *(torch.from_numpy(np.ascontiguousarray(v)) for v in (xx, aa, bb, tt)), half
    )
    got = d.amin(dim=(1, 2)).numpy()
    for p in range(n_pts):
        ref = min(_naive_piece_distance(x[p], a[e], b[e], 0.5, 0.5) for e in range(n_edges))
        assert got[p] == pytest.approx(_smooth(ref), abs=1e-9)


def test_point_to_edge_distance_degenerate_edge_and_smooth_zero():
    # a == b: the distance to the point a
    a = torch.tensor([[3.0, 4.0]], dtype=torch.float64)
    x = torch.tensor([[0.0, 0.0]], dtype=torch.float64)
    d = point_to_edge_distance(x, a, a.clone(), torch.tensor([0.5]).double(), 0.5)
    torch.testing.assert_close(
        d, torch.tensor([_smooth(5.0)], dtype=torch.float64), atol=1e-12, rtol=0
    )
    # a point on the piece: ~0 with a finite (zero) gradient
    xs = torch.tensor([[1.0, 1.0]], dtype=torch.float64, requires_grad=True)
    a0 = torch.tensor([[0.0, 0.0]], dtype=torch.float64)
    b0 = torch.tensor([[2.0, 2.0]], dtype=torch.float64)
    d0 = point_to_edge_distance(xs, a0, b0, torch.tensor([0.5]).double(), 0.25)
    assert abs(float(d0.detach())) < 1e-12
    d0.sum().backward()
    assert torch.isfinite(xs.grad).all() and float(xs.grad.abs().max()) < 1e-9


def test_point_to_edge_distance_gradcheck():
    g = torch.Generator().manual_seed(4)
    n = 6
    x = torch.rand(n, 2, generator=g, dtype=torch.float64) * 20
    a = torch.rand(n, 2, generator=g, dtype=torch.float64) * 20
    b = a + torch.randn(n, 2, generator=g, dtype=torch.float64) * 8
    t0 = torch.full((n,), 0.375, dtype=torch.float64)
    # keep away from the clamp kinks, where the derivative jumps
    d = b - a
    t = ((x - a) * d).sum(-1) / (d * d).sum(-1)
    assert ((t - 0.25).abs() > 0.05).all() and ((t - 0.5).abs() > 0.05).all()
    inputs = tuple(v.clone().requires_grad_() for v in (x, a, b, t0))
    assert torch.autograd.gradcheck(lambda *v: point_to_edge_distance(*v, 0.125), inputs, atol=1e-6)


def _trunk_and_arm() -> tuple[EdgeSampler, torch.Tensor]:
    """Two rectangles 4 px apart: a trunk (u 10-30) and an arm (u 34-40), v 10-50."""
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    pix = torch.cat([_square(10.0, 10.0, 30.0, 50.0), _square(34.0, 10.0, 40.0, 50.0)])
    return EdgeSampler(faces, samples_per_edge=4), pix[None]


def test_oriented_choice_pairs_a_pixel_with_a_sample_facing_its_way():
    s, pix = _trunk_and_arm()
    # the right side of the person's trunk at u = 33, facing right (+u): nearest in the image
    # is the arm's left side (1 px, facing left), the trunk's right side is 3 px off
    v = torch.arange(15.0, 46.0, 3.0, dtype=torch.float64)
    person = torch.stack([torch.full_like(v, 33.0), v], 1)[None]
    valid = torch.ones(1, v.numel(), dtype=torch.bool)
    normals = torch.tensor([1.0, 0.0]).expand(1, v.numel(), 2)
    plain = select_contour(s, pix, person, valid, (64, 64), 1.0)
    oriented = select_contour(s, pix, person, valid, (64, 64), 1.0, normals, 8.0)
    for sel, side_u in ((plain, 34.0), (oriented, 30.0)):
        paired = torch.gather(sel.samples[0], 0, sel.nearest[0])
        u = s.all_points(pix)[0, paired, 0]
        assert torch.allclose(u, torch.full_like(u, side_u))
    # without normals, or at 0 px, the choice is the plain one
    for sel in (
        select_contour(s, pix, person, valid, (64, 64), 1.0, None, 8.0),
        select_contour(s, pix, person, valid, (64, 64), 1.0, normals, 0.0),
    ):
        assert torch.equal(sel.nearest, plain.nearest) and torch.equal(sel.samples, plain.samples)


def test_outward_normals_of_the_chosen_samples_point_out_of_their_rectangle():
    s, pix = _trunk_and_arm()
    person = torch.zeros(1, 1, 2, dtype=torch.float64)
    sel = select_contour(s, pix, person, torch.ones(1, 1, dtype=torch.bool), (64, 64))
    chosen = sel.samples[0][sel.sample_valid[0]].numpy()
    n = outward_normals(s, pix[0].numpy(), chosen)
    pts = s.all_points(pix)[0, chosen].numpy()
    centre = np.where(pts[:, :1] < 32, [[20.0, 30.0]], [[37.0, 30.0]])
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    # each normal is an axis, pointing from its rectangle's centre through the sample
    assert ((n * (pts - centre)).sum(1) > 0).all()
    assert np.allclose(np.abs(n).max(1), 1.0)
