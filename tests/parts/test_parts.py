"""Tests of torchfit.parts: curvature extrema, the cactus rules, triangulation, failures."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torchfit.camera import Camera, look_at, project_points
from torchfit.image import trace_outer_contour
from torchfit.parts import (
    PartsError,
    curvature_extrema,
    decompose_cactus,
    fit_contour_spline,
    initial_guess_2d,
    stereo_measurements,
    triangulate_midpoint,
    undistort_pixels,
)


def _cactus(width: int = 11) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A thick stick figure in posture 5 drawn with cv2 and its skeleton points (u, v)."""
    j = {
        "head": (200, 60),
        "neck": (200, 105),
        "l_shoulder": (240, 125),
        "r_shoulder": (160, 125),
        "l_elbow": (300, 125),
        "r_elbow": (100, 125),
        "l_hand": (300, 55),
        "r_hand": (100, 55),
        "back": (200, 240),
        "l_foot": (235, 370),
        "r_foot": (165, 370),
    }
    m = np.zeros((400, 400), np.uint8)
    cv2.circle(m, j["head"], 22, 1, -1)
    cv2.rectangle(m, (172, 120), (228, 245), 1, -1)  # trunk
    cv2.line(m, (200, 80), j["neck"], 1, 16)
    for s in "lr":
        cv2.line(m, (200, 125), j[f"{s}_elbow"], 1, 2 * width)  # upper arm
        cv2.line(m, j[f"{s}_elbow"], j[f"{s}_hand"], 1, 2 * width - 4)  # forearm
        hip = (185 if s == "r" else 215, 240)
        cv2.line(m, hip, j[f"{s}_foot"], 1, 28)
    m = cv2.GaussianBlur(m.astype(np.float32), (0, 0), 1.5) > 0.5
    return m, {k: np.array(v, float) for k, v in j.items()}


def test_curvature_of_a_circle_and_extrema_of_a_rounded_square():
    m = np.zeros((200, 200), np.uint8)
    cv2.circle(m, (100, 100), 60, 1, -1)
    sp = fit_contour_spline(trace_outer_contour(m), smoothing=1.0)
    t, _ = sp.sample(2.0)
    k = sp.curvature(t)
    np.testing.assert_allclose(np.median(k), 1 / 60.0, rtol=0.03)
    assert (k > 0).all()  # convex everywhere, whatever the traversal direction
    # A plus sign: 4 concave corners (negative minima) and convex arm ends.
    m = np.zeros((200, 200), np.uint8)
    cv2.rectangle(m, (80, 20), (120, 180), 1, -1)
    cv2.rectangle(m, (20, 80), (180, 120), 1, -1)
    sp = fit_contour_spline(trace_outer_contour(m), smoothing=1.0)
    ext = curvature_extrema(sp, min_curvature=0.05, min_separation_px=8.0)
    minima = np.array([e.point for e in ext if e.kind == "min"])
    assert len(minima) == 4
    expected = np.array([[80, 80], [120, 80], [120, 120], [80, 120]], float)
    for p in expected:
        assert np.min(np.linalg.norm(minima - p, axis=1)) < 4.0
    assert sum(e.kind == "max" for e in ext) == 8  # two corners at each arm end


def test_curvature_sign_does_not_depend_on_direction():
    m = np.zeros((120, 120), np.uint8)
    cv2.ellipse(m, (60, 60), (40, 20), 0, 0, 360, 1, -1)
    c = trace_outer_contour(m).numpy()
    a = fit_contour_spline(c, smoothing=0.5)
    b = fit_contour_spline(c[::-1].copy(), smoothing=0.5)
    ta, _ = a.sample(2.0)
    tb, _ = b.sample(2.0)
    assert a.curvature(ta).min() > 0 and b.curvature(tb).min() > 0


def test_rules_on_a_cactus_stick_figure():
    mask, j = _cactus()
    lab = decompose_cactus(mask)
    assert lab.ok, lab.message
    raw = lab.raw_joints
    # The person's left is on the image right.
    assert raw["l_elbow"][0] > raw["r_elbow"][0]
    np.testing.assert_allclose(raw["neck"][0], 200, atol=2)
    assert 80 < raw["neck"][1] < 125
    for s in "lr":
        assert np.linalg.norm(raw[f"{s}_elbow"] - j[f"{s}_elbow"]) < 8
        sh = raw[f"{s}_shoulder"]
        assert abs(sh[1] - 125) < 15 and abs(sh[0] - j[f"{s}_shoulder"][0]) < 20
    assert abs(lab.landmarks["crotch"][0] - 200) < 3 and 240 < lab.landmarks["crotch"][1] < 270


def test_blob_without_arms_fails_with_a_named_rule():
    m = np.zeros((300, 200), np.uint8)
    cv2.ellipse(m, (100, 150), (40, 120), 0, 0, 360, 1, -1)
    lab = decompose_cactus(m.astype(bool))
    assert not lab.ok and lab.joints == {}
    assert lab.failed_rule == "extremities"
    assert "hand" in lab.message


def test_figure_without_neck_concavity_fails_at_neck():
    mask, _ = _cactus()
    mask = mask.copy()
    mask[30:125, 150:250] = True  # a box over head and neck: no concavity beside the head
    lab = decompose_cactus(mask)
    assert not lab.ok
    assert lab.failed_rule in ("neck", "extremities")


def test_initial_guess_interface():
    mask, _ = _cactus()
    stand = np.zeros_like(mask)
    stand[50:380, 170:230] = True
    guess = initial_guess_2d(mask, stand)
    assert guess.status == "ok"
    assert set(guess.joints_pose5) >= {"back", "neck", "l_shoulder", "r_elbow"}
    assert guess.extents_pose1.head_top[1] == 50 and guess.extents_pose1.lowest_foot[1] == 379
    assert guess.extents_pose1.width_px == 60
    bad = initial_guess_2d(mask, np.zeros_like(mask))
    assert bad.status == "failed" and bad.failed_rule == "pose1"
    with pytest.raises(PartsError, match="mask_pose5"):
        initial_guess_2d(np.zeros((2, 3, 4)), stand)


def _stereo_pair(dist=(0.0, 0.0, 0.0, 0.0, 0.0)):
    K = torch.tensor([[640.0, 0, 360], [0, 640, 288], [0, 0, 1]], dtype=torch.float64)
    cams = []
    for x in (-0.12, 0.12):
        R, t = look_at(
            torch.tensor([[x, -3.3, 1.2]], dtype=torch.float64),
            torch.tensor([[x, 0.0, 1.1]], dtype=torch.float64),
        )
        cams.append(Camera(K, torch.tensor(dist, dtype=torch.float64), R[0], t[0], (720, 576)))
    return cams


def test_midpoint_triangulation_recovers_known_points():
    left, right = _stereo_pair((-0.03, 0.02, 0.0004, -0.0001, 0.0))
    X = torch.tensor([[[0.1, 0.05, 1.5], [-0.4, 0.0, 1.45], [0.0, 0.1, 1.0]]], dtype=torch.float64)
    pl, pr = project_points(X, left), project_points(X, right)
    Y, gap = triangulate_midpoint(pl, left, pr, right)
    torch.testing.assert_close(Y, X, atol=1e-7, rtol=0)
    assert float(gap.max()) < 1e-7
    # A pixel off in one view: the rays miss each other and the gap says so.
    _, gap = triangulate_midpoint(pl, left, pr + torch.tensor([0.0, 3.0]), right)
    assert float(gap.min()) > 1e-3


def test_undistort_matches_opencv():
    left, _ = _stereo_pair((-0.08, 0.05, 0.001, -0.0005, 0.01))
    px = torch.tensor([[[10.0, 20.0], [700.0, 560.0], [360.0, 288.0], [100.0, 500.0]]])
    px = px.double()
    ours = undistort_pixels(px, left)[0].numpy()
    ref = cv2.undistortPoints(px[0].numpy()[:, None], left.K[0].numpy(), left.dist[0].numpy())[:, 0]
    np.testing.assert_allclose(ours, ref, atol=1e-6)


def test_stereo_measurements_and_errors():
    z = lambda *v: torch.tensor([v], dtype=torch.float64)  # noqa: E731
    joints = {
        "back": z(0, 0, 1.0),
        "neck": z(0, 0, 1.5),
        "l_shoulder": z(0.2, 0, 1.5),
        "r_shoulder": z(-0.2, 0, 1.5),
        "l_elbow": z(0.5, 0, 1.5),
        "r_elbow": z(-0.5, 0, 1.5),
        "l_wrist": z(0.5, 0, 1.75),
        "r_wrist": z(-0.5, 0, 1.75),
    }
    m = stereo_measurements(joints)
    torch.testing.assert_close(m["trunk_m"], z(0.5)[0])
    torch.testing.assert_close(m["upper_arm_m"], z(0.3)[0])
    torch.testing.assert_close(m["forearm_m"], z(0.25)[0])
    torch.testing.assert_close(m["virtual_leg_m"], z(1.0)[0])
    with pytest.raises(PartsError, match="missing"):
        stereo_measurements({"back": joints["back"]})
    with pytest.raises(PartsError, match="points"):
        fit_contour_spline(np.zeros((5, 3)))
