"""benchmarks/oracle_joints.py: the joint-pixel rows it adds to a problem (no fits), with and
without the shipped bend marks (whose rows the joint rows must follow)."""

import pytest
import torch
from central_differences import perturbed_start, residual_differences
from scripts import load_script
from template_subjects import make_template_subject, segment_subjects

from torchfit.camera import project_points, stack_cameras
from torchfit.fit import person_data_from_masks
from torchfit.fit.bends import BendFit, BendOptions
from torchfit.fit.prior import PriorFit, PriorOptions
from torchfit.io.dataset import load_subject


@pytest.fixture(scope="module")
def tool():
    return load_script("benchmarks/oracle_joints.py")


@pytest.fixture(scope="module")
def subject(tmp_path_factory, model):
    root = tmp_path_factory.mktemp("oracle")
    make_template_subject(root / "s", model, scale=1.02, seed=7)
    return load_subject(root / "s")


@pytest.mark.parametrize("problem", ["prior", "bends"])
def test_joint_rows_are_the_weighted_pixel_errors_and_their_jacobian(tool, model, subject, problem):
    masks = segment_subjects([subject])  # (1, 6, H, W)
    person = person_data_from_masks(masks, stack_cameras([subject.camera]))
    person.silhouettes = {j: masks[:, j] for j in range(masks.shape[1])}
    options = PriorOptions(pose_weight=0.5)
    if problem == "prior":
        fit = PriorFit(model, person, prior_options=options)
    else:
        fit = BendFit(model, person, prior_options=options, bends=BendOptions(weight=1.0))
        assert fit.residual_layout.num_marks > 0
    size = fit.residual_layout.size
    targets = torch.tensor([[[200.0, 150.0], [190.0, 210.0]]], dtype=torch.float64)
    fit = tool.with_joint_rows(fit, targets, ["l_knee", "l_ankle"], 3, 2.0)
    assert fit.residual_layout.size == size + 4
    assert fit.residual_mask().shape[1] == size + 4
    assert fit.loss_units().shape[1] == size + 4
    assert bool(torch.isinf(fit.loss_units()[0, size:]).all())  # least squares
    x = perturbed_start(fit, 0.03, 5)
    # the rows: 2 * (the joints' pixels in posture 3 - the targets)
    _, origins = fit.pose_world(x, 3, torch.tensor([0]))
    segs = [model.template.joints[j] for j in ("l_knee", "l_ankle")]
    pixels = project_points(origins[:, segs], fit.camera)
    sel = fit.select(x)
    r = fit.residual(x, sel)
    torch.testing.assert_close(r[0, size:], (2.0 * (pixels - targets)).reshape(-1))
    # their Jacobian against central differences, and the pass's residual is residual()'s
    free = fit.stage_indices(["all"], joints=True, root=True)
    jac, r2 = fit.jacobian_and_residual(x, free, sel)
    assert jac.shape[1] == r.shape[1] == size + 4
    torch.testing.assert_close(r2, r)
    at = list(range(0, free.numel(), 7))
    fd = residual_differences(fit, x, sel, slice(size, None), free[at])
    torch.testing.assert_close(jac[:, size:, at], fd, atol=1e-4, rtol=1e-6)
    assert float(jac[0, size:].abs().sum()) > 0
    # dense in the solver's blocks: no block holds the joint rows
    for rows, _ in fit.jacobian_blocks(free):
        assert rows.stop <= size


def test_depth_rows_are_the_weighted_depth_errors_in_centimetres(tool, model, subject):
    person = person_data_from_masks(segment_subjects([subject]), stack_cameras([subject.camera]))
    fit = PriorFit(model, person, prior_options=PriorOptions(pose_weight=0.5))
    size = fit.residual_layout.size
    targets = torch.tensor([[3.0, 3.2]], dtype=torch.float64)
    fit = tool.with_joint_rows(fit, targets, ["l_hip", "r_shoulder"], 4, 1.5, depth=True)
    assert fit.residual_layout.size == size + 2
    x = perturbed_start(fit, 0.03, 9)
    # the rows: 1.5 * (the joints' camera-frame z in posture 4 - the targets) / 1 cm
    _, origins = fit.pose_world(x, 4, torch.tensor([0]))
    segs = [model.template.joints[j] for j in ("l_hip", "r_shoulder")]
    camera = fit.camera
    z = (origins[0, segs] @ camera.R[0].T + camera.t[0])[:, 2]
    sel = fit.select(x)
    r = fit.residual(x, sel)
    torch.testing.assert_close(r[0, size:], 1.5 * 100.0 * (z - targets[0]))
    free = fit.stage_indices(["all"], joints=True, root=True)
    jac, r2 = fit.jacobian_and_residual(x, free, sel)
    torch.testing.assert_close(r2, r)
    at = list(range(0, free.numel(), 5))
    fd = residual_differences(fit, x, sel, slice(size, None), free[at])
    torch.testing.assert_close(jac[:, size:, at], fd, atol=1e-4, rtol=1e-6)
    assert float(jac[0, size:].abs().sum()) > 0
