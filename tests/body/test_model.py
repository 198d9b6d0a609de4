"""The body model: shapes, scaling semantics, postures, Jacobians against finite differences."""

import math

import pytest
import torch
import torch.autograd.forward_ad as fwAD

from torchfit.body.model import axis_angle_to_matrix
from torchfit.body.postures import POSTURES, nominal_joint_angles, pose_nominal
from torchfit.errors import ModelError, ShapeError


def random_params(model, batch, seed=0):
    g = torch.Generator().manual_seed(seed)
    rand = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    lo, hi = model.joint_lower, model.joint_upper
    return {
        "scales": 0.8 + 0.4 * rand(batch, model.num_segments, 3),
        "joint_angles": lo + (hi - lo) * (0.25 + 0.5 * rand(batch, model.num_dofs)),
        "root_translation": rand(batch, 3) - 0.5,
        "root_rotation": 2 * rand(batch, 3) - 1,
    }


def test_shapes(model):
    out = model(**random_params(model, 3))
    v = model.template.vertices.shape[0]
    assert out.vertices.shape == (3, v, 3)
    assert out.origins.shape == (3, model.num_segments, 3)
    assert out.rotations.shape == (3, model.num_segments, 3, 3)
    assert out.transforms.shape == (3, model.num_segments, 4, 4)
    eye = torch.eye(3, dtype=torch.float64).expand(3, model.num_segments, 3, 3)
    torch.testing.assert_close(out.rotations @ out.rotations.transpose(-1, -2), eye)


def test_neutral_pose_reproduces_the_template(model):
    out = model(**model.zeros(1))
    t = model.template
    expected = t.vertices + out.origins[0, t.vertex_segment]
    torch.testing.assert_close(out.vertices[0], expected)


def test_batch_rows_are_independent(model):
    p = random_params(model, 4)
    full = model(**p).vertices
    for i in range(4):
        one = model(**{k: v[i : i + 1] for k, v in p.items()}).vertices
        torch.testing.assert_close(full[i : i + 1], one)


def test_scaling_a_segment_moves_its_children(model):
    p = model.zeros(2)
    thigh = model.template.segment_index("l_thigh")
    p["scales"][1, thigh, 2] = 1.25
    out = model(**p)
    j = [model.joint_positions(out)[n] for n in ("l_hip", "l_knee", "l_ankle", "r_knee")]
    hip, knee, ankle, rknee = j
    torch.testing.assert_close(
        torch.linalg.vector_norm(knee[1] - hip[1]),
        1.25 * torch.linalg.vector_norm(knee[0] - hip[0]),
    )
    # the ankle moves down with the knee; the shank keeps its length; the right leg is untouched
    torch.testing.assert_close(ankle[1] - knee[1], ankle[0] - knee[0])
    torch.testing.assert_close(rknee[1], rknee[0])
    # the thigh's own mesh is stretched along its z axis only
    sel = model.template.vertex_segment == thigh
    rel0 = out.vertices[0, sel] - hip[0]
    rel1 = out.vertices[1, sel] - hip[1]
    torch.testing.assert_close(rel1, rel0 * torch.tensor([1.0, 1.0, 1.25], dtype=torch.float64))


def test_expand_scales_shares_left_right(model):
    g = torch.arange(model.num_groups * 3, dtype=torch.float64).reshape(1, -1, 3)
    s = model.expand_scales(g)
    idx = model.template.segment_index
    torch.testing.assert_close(s[0, idx("l_forearm")], s[0, idx("r_forearm")])
    with pytest.raises(ShapeError, match=r"group_scales: expected shape \(B, 12, 3\)"):
        model.expand_scales(torch.ones(1, 5, 3))


def test_axis_angle_matches_closed_form():
    angle = 0.7
    r = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, angle]], dtype=torch.float64))[0]
    c, s = math.cos(angle), math.sin(angle)
    expected = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(r, expected)
    torch.testing.assert_close(
        axis_angle_to_matrix(torch.zeros(2, 3, dtype=torch.float64)),
        torch.eye(3, dtype=torch.float64).expand(2, 3, 3),
    )


def test_wrong_shapes_are_named(model):
    p = model.zeros(2)
    p["joint_angles"] = torch.zeros(2, 7, dtype=torch.float64)
    with pytest.raises(ShapeError, match=r"joint_angles: expected shape \(2, 43\), got \(2, 7\)"):
        model(**p)
    with pytest.raises(ModelError, match="no joint DOF 'l_tail_wag'"):
        model.dof_index("l_tail_wag")


# ------------------------------------------------------------------------------------------
# Jacobians: autograd (reverse and forward mode) against central differences, float64

NAMES = ("scales", "joint_angles", "root_translation", "root_rotation")


def central_difference(model, params, name, index, h=1e-6):
    plus = {k: v.clone() for k, v in params.items()}
    minus = {k: v.clone() for k, v in params.items()}
    plus[name].view(plus[name].shape[0], -1)[:, index] += h
    minus[name].view(minus[name].shape[0], -1)[:, index] -= h
    return (model(**plus).vertices - model(**minus).vertices) / (2 * h)


@pytest.mark.parametrize("name", NAMES)
def test_reverse_mode_jacobian_matches_finite_differences(model, name):
    params = random_params(model, 2, seed=3)
    x = params[name].clone().requires_grad_(True)
    out = model(**{**params, name: x}).vertices
    # a random projection of the vertices: its gradient is J^T w for every parameter at once
    w = torch.randn(out.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    (grad,) = torch.autograd.grad((out * w).sum(), x)
    flat = grad.reshape(2, -1)
    for index in range(flat.shape[1]):
        fd = (central_difference(model, params, name, index) * w).sum(dim=(1, 2))
        torch.testing.assert_close(flat[:, index], fd, rtol=1e-6, atol=1e-7)


def test_forward_mode_with_tangents_folded_into_the_batch(model):
    """All P tangent directions in one call: the batch row b*P + p carries direction p."""
    params = random_params(model, 2, seed=5)
    x = params["joint_angles"]
    b, q = x.shape
    rep = {k: v.repeat_interleave(q, dim=0) for k, v in params.items()}
    tangents = torch.eye(q, dtype=torch.float64).repeat(b, 1)
    with fwAD.dual_level():
        dual = fwAD.make_dual(rep["joint_angles"], tangents)
        out = model(**{**rep, "joint_angles": dual}).vertices
        jac = fwAD.unpack_dual(out).tangent.reshape(b, q, -1, 3)
    for index in (0, 7, q // 2, q - 1):
        fd = central_difference(model, params, "joint_angles", index)
        torch.testing.assert_close(jac[:, index], fd, rtol=1e-6, atol=1e-7)


# ------------------------------------------------------------------------------------------
# Postures (design.md section 4)


def posed(model, posture, azimuth=0.7):
    centre = torch.tensor([3.5 * math.cos(azimuth), 3.5 * math.sin(azimuth), 1.2])
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    _, out = pose_nominal(model, scales, posture, centre.double())
    return model.joint_positions(out), out, centre.double()


def test_postures_stand_on_the_floor_facing_the_camera(model):
    for posture in POSTURES:
        joints, out, centre = posed(model, posture.index)
        assert out.vertices[0, :, 2].min().abs() < 1e-9
        forward = out.rotations[0, 0, :, 0]  # root x axis in the world
        to_cam = torch.nn.functional.normalize(
            centre * torch.tensor([1.0, 1.0, 0.0]).double(), dim=0
        )
        expected = 1.0 if posture.turn_deg == 0 else 0.0
        assert float(forward @ to_cam) == pytest.approx(expected, abs=1e-9)
        if posture.turn_deg:  # left side towards the camera
            left = out.rotations[0, 0, :, 1]
            assert float(left @ to_cam) == pytest.approx(1.0, abs=1e-9)


def test_posture_geometry(model):
    j, _, _ = posed(model, 4)  # T-pose: arms horizontal
    for s in "lr":
        assert abs(float(j[f"{s}_wrist"][0, 2] - j[f"{s}_shoulder"][0, 2])) < 0.02
    j, _, _ = posed(model, 5)  # cactus: forearms up, elbows at shoulder height
    for s in "lr":
        assert float(j[f"{s}_wrist"][0, 2] - j[f"{s}_elbow"][0, 2]) > 0.2
        assert abs(float(j[f"{s}_elbow"][0, 2] - j[f"{s}_shoulder"][0, 2])) < 0.02
    j, out, _ = posed(model, 3)  # side_knee: left shank horizontal, arms forward
    forward = out.rotations[0, 0, :, 0]
    shank = j["l_ankle"][0] - j["l_knee"][0]
    assert abs(float(shank[2])) < 0.02 and float(shank @ forward) < -0.3
    assert float((j["l_wrist"][0] - j["l_shoulder"][0]) @ forward) > 0.4


def test_nominal_angles_errors(model):
    with pytest.raises(ModelError, match="posture must be 1..6"):
        nominal_joint_angles(model.dof_names, 7)
    with pytest.raises(ModelError, match="needs joint DOF 'l_shoulder_abduct'"):
        nominal_joint_angles(["vc4_tilt"], 1)
