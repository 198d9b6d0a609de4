"""BodyModel.pose_jacobian: the closed-form pose derivatives of posed vertices against central
differences of the forward pass, for random poses, scales and root rotations (near zero too)."""

import pytest
import torch

from torchfit.body.model import BodyModel


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
