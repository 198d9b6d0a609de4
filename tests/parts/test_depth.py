"""Tests of torchfit.parts.depth: joint depths from the whole matched outline.

Reference: two known pinhole cameras (``look_at``, no distortion, 0.24 m apart, parallel axes
as in the synthetic rig) view a flat T-shaped plate in the plane ``y = 0`` facing them: a
trunk with a horizontal arm, whose upper and lower edges run along the epipolar lines. The
true depth of any left pixel on the plate is where its viewing ray meets that plane.
Silhouettes are the projected plate's pixel coverage (8x8 supersampling).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torchfit.camera import Camera, look_at, project_points
from torchfit.parts.depth import (
    joints_at_depth,
    local_plane_depth,
    outline_depths,
    weighted_median,
)
from torchfit.parts.stereo import pixel_rays

SIZE = (720, 576)
# a T: a trunk 0.4 m wide from z = 0.6 to 1.5, and an arm 0.12 m high out to x = 0.75
PLATE = np.array([[-0.2, 0.0, 0.6], [0.2, 0.0, 0.6], [0.2, 0.0, 1.3], [0.75, 0.0, 1.3],
                  [0.75, 0.0, 1.42], [0.2, 0.0, 1.5], [-0.2, 0.0, 1.5]])  # fmt: skip


def _camera(x: float) -> Camera:
    K = torch.tensor([[640.0, 0, 360], [0, 640, 288], [0, 0, 1]], dtype=torch.float64)
    R, t = look_at(
        torch.tensor([[x, -3.3, 1.6]], dtype=torch.float64),  # above the plate, looking down
        torch.tensor([[x, 0.0, 1.0]], dtype=torch.float64),
    )
    return Camera(K, torch.zeros(5, dtype=torch.float64), R[0], t[0], SIZE)


def _project(points: np.ndarray, camera: Camera) -> np.ndarray:
    return project_points(torch.tensor(points, dtype=torch.float64)[None], camera)[0].numpy()


def _silhouette(camera: Camera, ss: int = 8) -> np.ndarray:
    w, h = SIZE
    mask = np.zeros((h * ss, w * ss), np.uint8)
    poly = np.round(((_project(PLATE, camera) + 0.5) * ss - 0.5) * 16).astype(np.int32)
    cv2.fillPoly(mask, [poly], 1, lineType=cv2.LINE_8, shift=4)
    return mask.reshape(h, ss, w, ss).mean(axis=(1, 3))


def _true_depth(pixels: np.ndarray, camera: Camera) -> np.ndarray:
    """Left-camera depth where each pixel's ray meets the plate's plane y = 0."""
    o, d = pixel_rays(torch.tensor(pixels, dtype=torch.float64)[None], camera)
    s = -o[0, :, 1] / d[0, :, 1]
    X = o[0] + s[:, None] * d[0]
    return (X @ camera.R[0].T + camera.t[0])[:, 2].numpy()


@pytest.fixture(scope="module")
def scene():
    left, right = _camera(-0.12), _camera(0.12)
    ml, mr = _silhouette(left), _silhouette(right)
    guess = np.median(_project(PLATE, right) - _project(PLATE, left), axis=0)
    return left, right, ml > 0.5, mr > 0.5, guess + np.array([3.0, 0.0])  # guess 3 px off


def test_outline_depths_are_the_plates_depth_and_ignore_edges_along_the_epipolar_line(scene):
    left, right, ml, mr, guess = scene
    outline = outline_depths(ml, mr, guess, left, right)
    used = outline.weights > 0
    assert used.sum() > 50
    error = np.abs(outline.depths[used] - _true_depth(outline.points[used], left))
    # one pixel of disparity is ~7 cm at 3.3 m; the binary masks' staircase on slanted edges
    # limits a single match to a fraction of a pixel
    assert np.median(error) < 0.02 and np.percentile(error, 90) < 0.04
    # the arm's horizontal edges (between the trunk and the arm's end) carry no weight
    arm = _project(PLATE[[2, 3, 4, 5]], left)
    on_arm_edge = (
        (outline.points[:, 0] > arm[0, 0] + 5)
        & (outline.points[:, 0] < arm[1, 0] - 5)
        & ((outline.points[:, 1] < arm[1, 1] + 3) | (outline.points[:, 1] > arm[2, 1] - 3))
        & (outline.points[:, 1] > arm[3, 1] - 3)
    )
    assert on_arm_edge.sum() > 20
    assert np.all(outline.weights[on_arm_edge] == 0)


def test_joints_at_depth_recover_points_on_the_arm(scene):
    left, right, ml, mr, guess = scene
    outline = outline_depths(ml, mr, guess, left, right)
    truth = {
        "elbow": np.array([0.45, 0.0, 1.36]),  # middle of the arm: only horizontal edges near
        "neck": np.array([0.0, 0.0, 1.45]),
        "back": np.array([0.0, 0.0, 0.8]),
    }
    rng = np.random.default_rng(0)
    jl = {n: _project(X[None], left)[0] + rng.uniform(-1, 1, 2) for n, X in truth.items()}
    jr = {n: _project(X[None], right)[0] + rng.uniform(-1, 1, 2) for n, X in truth.items()}
    jl["left_only"] = np.zeros(2)
    joints, spread = joints_at_depth(outline, jl, jr, left, right, sigma_px=150.0)
    assert set(joints) == set(spread) == set(truth)
    for name, X in truth.items():
        assert np.linalg.norm(np.subtract(joints[name], X)) < 0.03, name
        assert spread[name] < 0.02  # the two labelled rays meet near that depth


def test_weighted_median():
    v = np.array([5.0, 1.0, 3.0, 100.0])
    assert weighted_median(v, np.array([1.0, 1.0, 1.0, 0.0])) == 3.0
    assert weighted_median(v, np.array([0.0, 0.0, 0.0, 1.0])) == 100.0
    assert weighted_median(v, np.array([1.0, 10.0, 1.0, 1.0])) == 1.0
    assert np.isnan(weighted_median(v, np.zeros(4)))


def test_local_plane_depth_is_exact_on_a_plane_and_ignores_outliers():
    rng = np.random.default_rng(1)
    points = rng.uniform(0, 400, size=(200, 2))
    depth = 3.0 + 0.002 * points[:, 0] - 0.004 * points[:, 1]
    weights = rng.uniform(0.2, 1.0, size=200)
    at = np.array([120.0, 300.0])
    expected = 3.0 + 0.002 * 120 - 0.004 * 300
    assert local_plane_depth(points, depth, weights, at) == pytest.approx(expected, abs=1e-9)
    # a quarter of the points 0.5 m off (a badly matched stretch): the plane is unmoved
    bad = depth.copy()
    bad[:50] += 0.5
    assert local_plane_depth(points, bad, weights, at) == pytest.approx(expected, abs=1e-6)
    # the weighted median of a sloped set is off; the plane is what removes the slope
    assert abs(weighted_median(depth, weights) - expected) > 0.05
    # fewer than three weighted points: the weighted median
    w2 = np.zeros(200)
    w2[[3, 7]] = 1.0
    assert local_plane_depth(points, depth, w2, at) == weighted_median(depth, w2)
