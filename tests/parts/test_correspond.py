"""Tests of torchfit.parts.correspond: epipolar lines and silhouette matching along them.

Reference: two known pinhole cameras (``look_at``, no distortion) viewing a flat polygon that
faces them. Its outline is the same 3-D curve in both views, so the right-view pixel of a
known 3-D point on it (``project_points``) is the true match. Silhouettes are the projected
polygon's pixel coverage (filled with cv2 at 8x8 supersampling), so a sub-pixel match is
well defined; binary masks (1/16-pixel precision fill) are also checked, within their
half-pixel quantisation. Epipolar lines are checked against projections of points along the
left pixel's viewing ray.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torchfit.camera import Camera, look_at, project_points
from torchfit.parts.correspond import (
    corresponding_joints,
    epipolar_line,
    match_point,
    smooth_mask,
)

SIZE = (720, 576)
# a flat pentagon in the plane y = 0, facing the cameras (x right, z up), metres
PLATE = np.array([[-0.3, 0.0, 0.8], [0.25, 0.0, 0.7], [0.35, 0.0, 1.3], [0.0, 0.0, 1.6],
                  [-0.4, 0.0, 1.25]])  # fmt: skip


def _camera(x: float, target_x: float) -> Camera:
    K = torch.tensor([[640.0, 0, 360], [0, 640, 288], [0, 0, 1]], dtype=torch.float64)
    R, t = look_at(
        torch.tensor([[x, -3.3, 1.2]], dtype=torch.float64),
        torch.tensor([[target_x, 0.0, 1.1]], dtype=torch.float64),
    )
    return Camera(K, torch.zeros(5, dtype=torch.float64), R[0], t[0], SIZE)


def _rig(parallel: bool = False) -> tuple[Camera, Camera]:
    """A converging (or parallel-axis) pair 0.24 m apart, like the synthetic rig."""
    return _camera(-0.12, -0.12 if parallel else 0.0), _camera(0.12, 0.12 if parallel else 0.0)


def _project(points: np.ndarray, camera: Camera) -> np.ndarray:
    return project_points(torch.tensor(points, dtype=torch.float64)[None], camera)[0].numpy()


def _silhouette(camera: Camera, supersample: int = 1) -> np.ndarray:
    """(H, W) bool mask, or float pixel coverage with ``supersample`` > 1."""
    ss = supersample
    w, h = SIZE
    mask = np.zeros((h * ss, w * ss), np.uint8)
    # pixel (0, 0) is the centre of the top-left pixel: its sub-pixel i centres at (i + 0.5)/ss
    poly = np.round(((_project(PLATE, camera) + 0.5) * ss - 0.5) * 16).astype(np.int32)
    cv2.fillPoly(mask, [poly], 1, lineType=cv2.LINE_8, shift=4)
    if ss == 1:
        return mask.astype(bool)
    return mask.reshape(h, ss, w, ss).mean(axis=(1, 3))


def _dist_to_line(q: np.ndarray, q_c: np.ndarray, e: np.ndarray) -> float:
    r = q - q_c
    return float(abs(r[0] * e[1] - r[1] * e[0]))


@pytest.fixture(scope="module")
def scene():
    left, right = _rig()
    return left, right, _silhouette(left, 8), _silhouette(right, 8)


def test_epipolar_line_contains_the_projections_of_the_left_ray(scene):
    left, right, _, _ = scene
    X = np.array([0.1, 0.0, 1.2])
    p, q_true = _project(X[None], left)[0], _project(X[None], right)[0]
    q0 = q_true + np.array([3.0, -2.0])  # a scattered right label
    q_c, e = epipolar_line(p, q0, left, right)
    assert np.linalg.norm(e) == pytest.approx(1.0)
    assert (q0 - q_c) @ e == pytest.approx(0.0, abs=1e-9)  # q_c is the foot of q0
    # points along the left pixel's ray at any depth project onto the line
    cam_centre = left.centre[0].numpy()
    for depth in (1.5, 3.0, 3.3, 8.0):
        Y = cam_centre + depth * (X - cam_centre) / np.linalg.norm(X - cam_centre)
        assert _dist_to_line(_project(Y[None], right)[0], q_c, e) < 1e-6
    assert _dist_to_line(q_true, q_c, e) < 1e-6
    # e points towards smaller depths (larger disparity, here towards smaller u)
    near = cam_centre + 2.0 * (X - cam_centre) / np.linalg.norm(X - cam_centre)
    assert (_project(near[None], right)[0] - q_true) @ e > 0
    assert e[0] < 0


def test_epipolar_line_with_parallel_rays_falls_back_to_a_default_depth():
    # parallel optical axes and the same pixel in both views: the rays never meet
    left, right = _rig(parallel=True)
    p = np.array([400.0, 250.0])
    q_c, e = epipolar_line(p, p, left, right)
    assert np.isfinite(q_c).all() and np.isfinite(e).all()
    assert abs(e[1]) < 1e-9  # rectified pair: horizontal lines
    # the line is still p's epipolar line: the right image of a point on p's ray lies on it
    o = left.centre[0].numpy()
    ray = np.linalg.solve(left.K[0].numpy(), np.array([400.0, 250.0, 1.0]))
    Y = o + 3.0 * (left.R[0].numpy().T @ ray)
    assert _dist_to_line(_project(Y[None], right)[0], q_c, e) < 1e-6


@pytest.mark.parametrize("corner", [0, 2, 3])
def test_match_point_finds_the_true_right_pixel_of_a_corner(scene, corner):
    left, right, ml, mr = scene
    X = PLATE[corner]
    p, q_true = _project(X[None], left)[0], _project(X[None], right)[0]
    sl, sr = smooth_mask(ml), smooth_mask(mr)
    for offset in (-3.0, 0.0, 2.5):  # label scatter along the line
        q_c, e = epipolar_line(p, q_true + offset * np.array([1.0, 0.0]), left, right)
        q, cost = match_point(sl, sr, p, q_c, e, radius_px=8, search_px=6)
        assert np.linalg.norm(q - q_true) < 0.15
        assert _dist_to_line(q, q_c, e) < 1e-9  # the answer lies on the line
        assert 0.0 <= cost < 1e-3


def test_match_point_on_a_slanted_edge(scene):
    left, right, ml, mr = scene
    X = 0.6 * PLATE[1] + 0.4 * PLATE[2]  # middle of the right-hand edge
    p, q_true = _project(X[None], left)[0], _project(X[None], right)[0]
    q_c, e = epipolar_line(p, q_true + np.array([-2.0, 1.0]), left, right)
    q, _ = match_point(smooth_mask(ml), smooth_mask(mr), p, q_c, e, radius_px=8, search_px=6)
    assert np.linalg.norm(q - q_true) < 0.15


def test_match_point_on_binary_masks_within_their_quantisation(scene):
    left, right, _, _ = scene
    sl, sr = smooth_mask(_silhouette(left)), smooth_mask(_silhouette(right))
    errors = []
    for i in range(len(PLATE)):  # corners and points along every edge
        for f in (0.0, 0.3, 0.6):
            X = (1 - f) * PLATE[i] + f * PLATE[(i + 1) % len(PLATE)]
            p, q_true = _project(X[None], left)[0], _project(X[None], right)[0]
            q_c, e = epipolar_line(p, q_true + np.array([2.0, 0.0]), left, right)
            q, _ = match_point(sl, sr, p, q_c, e, radius_px=8, search_px=6)
            errors.append(np.linalg.norm(q - q_true))
    assert max(errors) < 1.5 and np.mean(errors) < 0.5


def test_match_point_edge_cases(scene):
    left, right, ml, mr = scene
    sl, sr = smooth_mask(ml), smooth_mask(mr)
    # identical images and the same point: zero shift, zero cost (radius below 2 is raised to 2)
    p = _project(PLATE[:1], left)[0]
    q, cost = match_point(sl, sl, p, p, np.array([1.0, 0.0]), radius_px=0.4, search_px=3)
    np.testing.assert_allclose(q, p, atol=0.05)  # parabola refinement: within a fraction
    assert cost == 0.0
    # the true match beyond the search range: the answer stays within it, at the near end
    q_true = _project(PLATE[:1], right)[0]
    q_c, e = epipolar_line(p, q_true, left, right)
    start = q_c - 10.0 * e
    q, cost = match_point(sl, sr, p, start, e, radius_px=8, search_px=4)
    s = float((q - start) @ e)
    assert s == pytest.approx(4.0)
    assert cost > 1e-3
    # a flat region (inside the plate) matches everywhere: cost 0 and q within the range
    inside = _project(PLATE.mean(0)[None], left)[0]
    q_c, e = epipolar_line(inside, _project(PLATE.mean(0)[None], right)[0], left, right)
    q, cost = match_point(sl, sr, inside, q_c, e, radius_px=4, search_px=5)
    assert cost == pytest.approx(0.0, abs=1e-12)
    assert abs(float((q - q_c) @ e)) <= 5.0 + 1e-9


@pytest.mark.parametrize("parallel", [False, True])
def test_corresponding_joints_give_the_true_disparity(scene, parallel):
    left, right, ml, mr = scene
    if parallel:  # parallel axes: ~46 px of disparity instead of ~0 for the converging pair
        left, right = _rig(parallel=True)
        ml, mr = _silhouette(left, 8), _silhouette(right, 8)
    names = {"a": [0, 1], "b": [3], "c": [2, 4]}
    anchors_l, anchors_r, joints_l, joints_r, truth = {}, {}, {}, {}, {}
    rng = np.random.default_rng(0)
    for name, corners in names.items():
        pl, pr = _project(PLATE[corners], left), _project(PLATE[corners], right)
        anchors_l[name] = pl
        anchors_r[name] = pr + rng.uniform(-2.5, 2.5, size=pr.shape)  # scattered labels
        X = PLATE[corners].mean(0)
        truth[name] = (_project(X[None], left)[0], _project(X[None], right)[0])
        joints_l[name] = truth[name][0] + rng.uniform(-1, 1, size=2)
        joints_r[name] = truth[name][1] + rng.uniform(-1, 1, size=2)
    joints_l["left_only"] = np.zeros(2)  # not in the right view: skipped
    joints_r["no_anchors"] = joints_l["no_anchors"] = np.zeros(2)  # no anchors: skipped
    out_l, out_r = corresponding_joints(
        ml, mr, joints_l, joints_r, anchors_l, anchors_r, left, right, radius_px=8, search_px=6
    )
    assert set(out_l) == set(out_r) == set(names)
    for name, corners in names.items():
        true_disp = np.mean(
            _project(PLATE[corners], right) - _project(PLATE[corners], left), axis=0
        )
        np.testing.assert_allclose(out_r[name] - out_l[name], true_disp, atol=0.15)
        assert abs(true_disp[0]) > 40 if parallel else abs(true_disp[0]) < 5
        # the left pixel is the mean of the two labels brought into the left view
        np.testing.assert_allclose(
            out_l[name], 0.5 * (joints_l[name] + joints_r[name] - (out_r[name] - out_l[name]))
        )
    with pytest.raises(ValueError, match="zip"):
        corresponding_joints(
            ml, mr, {"a": joints_l["a"]}, {"a": joints_r["a"]}, {"a": anchors_l["a"]},
            {"a": anchors_r["a"][:1]}, left, right, 8, 6,
        )  # fmt: skip
