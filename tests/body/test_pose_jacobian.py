"""BodyModel.pose_jacobian and BodyModel.jacobian: the closed-form pose and scale derivatives
of posed vertices against central differences of the forward pass, for random poses, scales
and root rotations (near zero too)."""

import pytest
import torch

from torchfit.body.model import BodyModel, axis_angle_to_matrix


@pytest.fixture(scope="module")
def model():
    return BodyModel("mpeg4_full")


def _random_pose(model, batch: int, seed: int, root_angle: float):
    g = torch.Generator().manual_seed(seed)
    kw = {"generator": g, "dtype": torch.float64}
    scales = 0.8 + 0.4 * torch.rand(batch, model.num_segments, 3, **kw)
    span = model.joint_upper - model.joint_lower
    q = model.joint_lower + span * torch.rand(batch, model.num_dofs, **kw)
    t = torch.randn(batch, 3, **kw)
    axis = torch.nn.functional.normalize(torch.randn(batch, 3, **kw), dim=1)
    return scales, q, t, root_angle * axis


def _central(model, scales, x, index, h=1e-6):
    def pose(row):
        return model(scales, row[:, 6:], row[:, :3], row[:, 3:6], index).vertices

    cols = []
    for i in range(x.shape[1]):
        step = torch.zeros_like(x)
        step[:, i] = h
        cols.append((pose(x + step) - pose(x - step)) / (2 * h))
    return torch.stack(cols, -1)


@pytest.mark.parametrize("root_angle", [0.0, 1e-7, 0.7, 2.9])
def test_pose_jacobian_matches_central_differences(model, root_angle):
    scales, q, t, r = _random_pose(model, 3, seed=int(root_angle * 10), root_angle=root_angle)
    g = torch.Generator().manual_seed(1)
    index = torch.randperm(model.template.vertices.shape[0], generator=g)[:400]
    vertices, jac = model.pose_jacobian(scales, q, t, r, index)
    assert jac.shape == (3, 400, 3, 6 + model.num_dofs)
    torch.testing.assert_close(vertices, model(scales, q, t, r, index).vertices)
    x = torch.cat([t, r, q], 1)
    torch.testing.assert_close(jac, _central(model, scales, x, index), atol=1e-7, rtol=0)


def test_a_joint_moves_only_what_hangs_below_it(model):
    scales, q, t, r = _random_pose(model, 1, seed=5, root_angle=0.3)
    index = torch.arange(model.template.vertices.shape[0])
    _, jac = model.pose_jacobian(scales, q, t, r, index)
    seg = model.template.vertex_segment
    knee = 6 + model.dof_index("l_knee_flexion")
    moved = jac[0, :, :, knee].abs().amax(-1) > 0
    names = model.template.segments
    below = torch.tensor([names[s] in ("l_calf", "l_hindfoot") for s in seg.tolist()])
    assert torch.equal(moved, below)


@pytest.mark.parametrize("seed", [0, 1])
def test_scale_and_joint_jacobian_matches_central_differences(model, seed):
    """BodyModel.jacobian: every segment's three scales and every joint angle, with the root
    rotation held (a matrix), against central differences of the forward pass."""
    scales, q, t, r = _random_pose(model, 2, seed=seed, root_angle=0.8)
    rot = axis_angle_to_matrix(r)
    g = torch.Generator().manual_seed(seed)
    index = torch.randperm(model.template.vertices.shape[0], generator=g)[:300]
    out, d_scales, d_joints = model.jacobian(scales, q, t, rot, index)
    s = model.num_segments
    assert d_scales.shape == (2, 300, 3, s, 3) and d_joints.shape == (2, 300, 3, model.num_dofs)
    torch.testing.assert_close(out.vertices, model(scales, q, t, r, index).vertices)

    def pose(sc, qq):
        return model(sc, qq, t, rot, index).vertices

    h = 1e-6
    for seg in range(s):
        for a in range(3):
            step = torch.zeros_like(scales)
            step[:, seg, a] = h
            fd = (pose(scales + step, q) - pose(scales - step, q)) / (2 * h)
            torch.testing.assert_close(d_scales[..., seg, a], fd, atol=1e-7, rtol=0)
    for k in range(model.num_dofs):
        step = torch.zeros_like(q)
        step[:, k] = h
        fd = (pose(scales, q + step) - pose(scales, q - step)) / (2 * h)
        torch.testing.assert_close(d_joints[..., k], fd, atol=1e-7, rtol=0)


def test_a_scale_moves_only_its_segment_and_what_hangs_below_it(model):
    scales, q, t, r = _random_pose(model, 1, seed=7, root_angle=0.3)
    index = torch.arange(model.template.vertices.shape[0])
    _, d_scales, _ = model.jacobian(scales, q, t, axis_angle_to_matrix(r), index)
    names = model.template.segments
    thigh = names.index("l_thigh")
    moved = d_scales[0, :, :, thigh].abs().amax((-1, -2)) > 0
    seg = model.template.vertex_segment
    below = {thigh} | {s for s in range(len(names)) if _has_ancestor(model, s, thigh)}
    expected = torch.tensor([int(s) in below for s in seg.tolist()])
    assert torch.equal(moved, expected)
    assert expected.sum() < len(expected) // 3  # the leg only, not the body


def _has_ancestor(model, s: int, a: int) -> bool:
    parents = model.template.parents
    while parents[s] >= 0:
        s = int(parents[s])
        if s == a:
            return True
    return False


def test_the_kinematics_pass_handed_back_gives_the_same_jacobian_bitwise(model):
    """pose_pass poses the points as forward does, and pose_jacobian on it is pose_jacobian
    alone, bit for bit (the tracker's residual hands its pass to the Jacobian that follows)."""
    scales, q, t, r = _random_pose(model, 3, seed=11, root_angle=0.7)
    index = torch.arange(0, model.template.vertices.shape[0], 7)
    passed = model.pose_pass(scales, q, t, r, index)
    assert torch.equal(passed[2].vertices, model(scales, q, t, r, index).vertices)
    alone = model.pose_jacobian(scales, q, t, r, index)
    handed = model.pose_jacobian(scales, q, t, r, index, passed)
    assert torch.equal(alone[0], handed[0]) and torch.equal(alone[1], handed[1])


def test_a_pass_reposed_for_other_vertices_is_their_own_pass_bitwise(model):
    """repose keeps a pass's frames, rotations and origins and poses other vertices as a pose
    pass of them would (the tracker's next contour choice starts from its last solve's pass)."""
    scales, q, t, r = _random_pose(model, 3, seed=12, root_angle=2.0)
    some = torch.arange(0, model.template.vertices.shape[0], 7)
    every = torch.arange(model.template.vertices.shape[0])
    reposed = model.repose(model.pose_pass(scales, q, t, r, some), scales, every)
    own = model.pose_pass(scales, q, t, r, every)
    assert torch.equal(reposed[2].vertices, own[2].vertices)
    assert torch.equal(reposed[3], own[3])  # each vertex's segment
    assert torch.equal(reposed[2].vertices[:, some], model(scales, q, t, r, some).vertices)
