"""The fit's robust pieces on template subjects (no ../shared, no anny): posture weights in the
residual and its Jacobian, the robust loss's per-pixel units, the posture outlier rule, and a
band glued to an arm that pulls least squares and not Huber."""

import pytest
import torch
from central_differences import perturbed_start, residual_differences
from template_subjects import make_template_subject

from torchfit.body.measure import measure_model
from torchfit.camera import stack_cameras
from torchfit.fit import (
    FitOptions,
    SilhouetteFit,
    StageOptions,
    person_data_from_masks,
    solve_stage,
)
from torchfit.fit.stages import pose_contour_rms, pose_outliers
from torchfit.image import SegmentationOptions, fit_background, segment
from torchfit.io.dataset import load_subject
from torchfit.io.images import load_frames
from torchfit.solver import LMOptions


@pytest.fixture(scope="module")
def subject(tmp_path_factory, model):
    root = tmp_path_factory.mktemp("robust_subject")
    truth = make_template_subject(root / "tall", model, scale=1.06, seed=4)
    s = load_subject(root / "tall")
    cfg = SegmentationOptions(gamma=0.05)
    background, _ = load_frames(s.background)
    images, _ = load_frames(s.poses)
    masks = segment(images, fit_background(background, cfg), cfg).masks[:, 0]
    return s, masks[None], truth


def _problem(model, subject, masks, options=None):
    cams = stack_cameras([subject.camera])
    return SilhouetteFit(model, person_data_from_masks(masks, cams), options or FitOptions())


def test_pose_outlier_rule():
    rms = torch.tensor(
        [
            [1.0, 1.2, 0.9, 14.2, 1.1, 1.0],  # one posture far off
            [1.0, 1.2, 0.9, 3.5, 1.1, 1.0],  # 2.4 px over the median: under the 3 px floor
            [2.0, 2.5, 3.0, 3.5, 4.0, 4.5],  # a spread, no outlier
            [1.0, 30.0, 1.0, 30.0, 30.0, 30.0],  # at most half the postures, the worst first
        ],
        dtype=torch.float64,
    )
    out = pose_outliers(rms, 5.0, 3.0)
    assert out[0].tolist() == [False, False, False, True, False, False]
    assert not out[1].any() and not out[2].any()
    assert int(out[3].sum()) <= 3
    assert not pose_outliers(rms, None, 3.0).any()


def test_weighted_jacobian_matches_central_differences(model, subject):
    s, masks, _ = subject
    fit = _problem(model, s, masks)
    fit.pose_weights = torch.tensor([[1.0, 0.1, 0.5, 1.0, 0.3, 1.0]], dtype=torch.float64)
    x = perturbed_start(fit, 0.01, 1)
    sel = fit.select(x)
    jac = fit.jacobian(x, torch.arange(fit.num_params), sel)
    columns = range(0, fit.num_params, 7)
    diffs = residual_differences(fit, x, sel, slice(None), columns)
    for k, p in enumerate(columns):
        fd = diffs[..., k]
        torch.testing.assert_close(
            jac[:, :, p], fd, atol=2e-3 * max(float(fd.abs().max()), 1.0), rtol=0
        )
    # the weights scale the residual; pose_contour_rms undoes them
    w1 = _problem(model, s, masks)
    rms_w, _ = pose_contour_rms(fit, x)
    rms_1, _ = pose_contour_rms(w1, x)
    torch.testing.assert_close(rms_w, rms_1)


def test_loss_units_are_pixels_of_each_entry(model, subject):
    s, masks, _ = subject
    fit = _problem(model, s, masks)
    fit.pose_weights[0, 2] = 0.5
    units = fit.loss_units()
    rl = fit.residual_layout
    assert units.shape == (1, rl.size)
    for k, j in enumerate(fit.poses):
        n = int(fit.person.valid[k][0].sum())
        w = float(fit.pose_weights[0, k])
        torch.testing.assert_close(
            units[0, rl.e_p(j)][0], torch.tensor(w / n**0.5, dtype=torch.float64)
        )
        assert torch.isinf(units[0, rl.e_m(j)])
    assert torch.isinf(units[0, rl.barrier]).all()


def _glue_band(masks, pose_index):
    """A band of 'person' glued below the arm that reaches furthest sideways, running 60 % of
    the arm's reach past the hand (a wall shadow attached to the arm)."""
    out = masks.clone()
    m = out[0, pose_index]
    ys, xs = torch.nonzero(m, as_tuple=True)
    centre = int(xs.float().median())
    left, right = int(xs.min()), int(xs.max())
    tip, side = (left, -1) if centre - left > right - centre else (right, 1)
    row = int(ys[(xs - tip).abs() < 6].float().median())
    reach = abs(tip - centre)
    x0, x1 = sorted((tip - side * reach // 3, tip + side * int(0.6 * reach)))
    m[row : row + 8, max(x0, 0) : x1] = True
    return out


@pytest.mark.slow
@pytest.mark.parametrize(
    "loss",
    [
        "linear",
        pytest.param(
            "huber",
            marks=pytest.mark.xfail(
                strict=True,
                reason="a known regression: Huber leaves this arm span 4.3 % off (was < 2 % "
                "when the robust loss landed); see CHANGELOG",
            ),
        ),
    ],
)
def test_band_glued_to_an_arm_pulls_least_squares_not_huber(model, subject, loss):
    """The shipped schedule: a least-squares first stage, then the whole body with ``loss``."""
    s, masks, truth = subject
    damaged = _glue_band(_glue_band(masks, 3), 0)  # T-pose and pose 1
    fit = _problem(model, s, damaged)
    first = StageOptions(name="legs_upper_body", scales=("legs", "upper_body"))
    x, _ = solve_stage(fit, fit.initial_params(), first, LMOptions(max_iter=15, min_diag=1.0))
    options = LMOptions(max_iter=25, loss=loss, loss_scale=3.0, min_diag=1.0)
    x, _ = solve_stage(fit, x, StageOptions(name="all"), options)
    scales = model.expand_scales(fit.layout.group_scales(x))
    error = float(measure_model(model, scales)["arm_span_m"][0]) / truth["arm_span_m"] - 1
    if loss == "linear":
        assert error > 0.03, f"arm span {100 * error:.1f} %"
    else:
        assert abs(error) < 0.02, f"arm span {100 * error:.1f} %"
