"""Hip abduction in the side views: a depth movement that trades knee height for thigh length.

Posture 3 (side_knee) shows the flexed left knee from the side. Abducting that hip swings the
thigh along the line of sight; with the thigh lengthened and the shank shortened so that the
hip stays at its height, the knee can be brought back to the same pixel while its height,
the lower leg measurement, drops by centimetres. The silhouette cannot tell the two bodies
apart, so the side views keep hip abduction at its nominal 0.
"""

from __future__ import annotations

import math

import torch

from torchfit.body.measure import measure_model
from torchfit.body.postures import nominal_joint_angles
from torchfit.camera import Camera, project_points
from torchfit.fit.pose import DEFAULT_FREE_JOINTS


def _camera() -> Camera:
    """A camera 3.7 m to the body's left, 1.4 m high, looking at (0, 0, 0.9)."""
    centre = torch.tensor([0.0, 3.7, 1.4], dtype=torch.float64)
    forward = torch.tensor([0.0, 0.0, 0.9], dtype=torch.float64) - centre
    forward = forward / forward.norm()
    right = torch.linalg.cross(forward, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    R = torch.stack([right, down, forward])
    K = torch.tensor([[700.0, 0, 360], [0, 700.0, 288], [0, 0, 1]], dtype=torch.float64)
    return Camera(
        K=K, dist=torch.zeros(5, dtype=torch.float64), R=R, t=-R @ centre, image_size=(720, 576)
    )


def _posture3(model, thigh: float, calf: float, abduct_deg: float):
    """(knee pixel (2,), hip height, lower leg) of the template in posture 3 with the thigh and
    calf scale groups' lengths set, the left hip abducted, standing on the floor."""
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    for side in "lr":
        scales[0, model.template.segment_index(f"{side}_thigh"), 2] = thigh
        scales[0, model.template.segment_index(f"{side}_calf"), 2] = calf
    angles = nominal_joint_angles(model.dof_names, 3)[None].clone()
    angles[0, model.dof_index("l_hip_abduct")] = math.radians(abduct_deg)
    zero = torch.zeros(1, 3, dtype=torch.float64)
    joints = model.joint_positions(model(scales, angles, zero, zero))
    floor = torch.minimum(joints["l_sole"][:, 2], joints["r_sole"][:, 2])
    knee = joints["l_knee"] - torch.stack(
        [torch.zeros_like(floor), torch.zeros_like(floor), floor], -1
    )
    pixel = project_points(knee[:, None], _camera())[0, 0]
    hip = float(joints["r_hip"][0, 2] - floor[0])
    return pixel, hip, float(measure_model(model, scales)["lower_leg_m"][0])


def test_side_view_hip_abduction_hides_a_lower_knee(model):
    pixel0, hip0, lower0 = _posture3(model, 1.0, 1.0, 0.0)
    length = {
        g: float(model.offsets[model.template.segment_index(f"l_{c}"), 2].abs())
        for g, c in (("thigh", "calf"), ("calf", "hindfoot"))
    }

    def body(thigh: float):
        # the shank shortens by what the thigh gains: the hip keeps its height
        calf = 1.0 - (thigh - 1.0) * length["thigh"] / length["calf"]
        return _posture3(model, thigh, calf, -15.0)

    # the thigh length that puts the knee back on its pixel row (secant steps)
    a, b = 1.0, 1.1
    fa, fb = float(body(a)[0][1] - pixel0[1]), float(body(b)[0][1] - pixel0[1])
    for _ in range(8):
        if abs(fb) < 1e-6:
            break
        a, b, fa = b, b - fb * (b - a) / (fb - fa), fb
        fb = float(body(b)[0][1] - pixel0[1])
    pixel, hip, lower = body(b)
    assert abs(hip - hip0) < 2e-3
    assert torch.linalg.vector_norm(pixel - pixel0) < 1.0  # the same knee pixel
    assert b > 1.04  # a thigh more than 4 % longer
    assert lower0 - lower > 0.015  # and a knee more than 1.5 cm lower


def test_side_views_keep_hip_abduction_fixed():
    for j in (3, 6):
        assert not [d for d in DEFAULT_FREE_JOINTS[j] if d.endswith("hip_abduct")]
        assert "l_hip_flexion" in DEFAULT_FREE_JOINTS[j]
    for j in (1, 2, 4, 5):
        assert {"l_hip_abduct", "r_hip_abduct"} <= set(DEFAULT_FREE_JOINTS[j])


def test_the_neck_moves_only_across_the_line_of_sight():
    # the nod (vc4_tilt) is free where the camera sees the body from the side, the side bend
    # (vc4_roll) where it sees it from the front
    for j in (3, 6):
        assert "vc4_tilt" in DEFAULT_FREE_JOINTS[j]
        assert "vc4_roll" not in DEFAULT_FREE_JOINTS[j]
    for j in (1, 2, 4, 5):
        assert "vc4_roll" in DEFAULT_FREE_JOINTS[j]
        assert "vc4_tilt" not in DEFAULT_FREE_JOINTS[j]
