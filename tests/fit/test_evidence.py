"""What the images pay for a pinned quantity (torchfit.fit.evidence).

Checks: the pin's residual and its Jacobian row (central differences), a NaN target pins
nothing; pinning the arm span of a fitted body 5 % off what the T-pose shows reaches the target
and costs the images clearly more than a free refit, while pinning it where it already is costs
nothing.
"""

import math

import pytest
import torch
from template_subjects import make_template_subject

from torchfit.body.measure import measure_model
from torchfit.camera import stack_cameras
from torchfit.fit import SilhouetteFit, StageOptions, person_data_from_masks, solve_stage
from torchfit.fit.evidence import PinnedFit, image_cost, pinning_cost
from torchfit.image import SegmentationOptions, fit_background, segment
from torchfit.io.dataset import load_subject
from torchfit.io.images import load_frames
from torchfit.solver import LMOptions


@pytest.fixture(scope="module")
def problem(tmp_path_factory, model):
    root = tmp_path_factory.mktemp("evidence")
    make_template_subject(root / "s", model, scale=1.03, seed=11)
    subject = load_subject(root / "s")
    cfg = SegmentationOptions(gamma=0.05, shadow_test=False)
    background, _ = load_frames(subject.background)
    images, _ = load_frames(subject.poses)
    masks = segment(images, fit_background(background, cfg), cfg).masks[:, 0]
    person = person_data_from_masks(masks[None], stack_cameras([subject.camera]))
    return SilhouetteFit(model, person)


def _span_ratio(fit):
    def ratio(full: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        scales = fit.model.expand_scales(fit.layout.group_scales(full))
        m = measure_model(fit.model, scales)
        return m["arm_span_m"] / m["height_m"]

    return ratio


def test_pin_residual_and_jacobian_row(problem):
    fit = problem.subset([0, 0])
    g = torch.Generator().manual_seed(3)
    x = fit.initial_params() + 0.02 * torch.randn(
        2, fit.num_params, generator=g, dtype=torch.float64
    )
    ratio = _span_ratio(fit)
    tolerance = torch.tensor([1e-4, 1e-4], dtype=torch.float64)
    pinned = PinnedFit(fit, ratio, torch.tensor([1.1, math.nan], dtype=torch.float64), tolerance)
    sel = fit.select(x)
    r = pinned.residual(x, sel)
    assert r.shape[1] == fit.residual_layout.size + 1
    q = ratio(x, torch.arange(2))
    assert float(r[0, -1]) == pytest.approx(float(q[0] - 1.1) / 1e-4)
    assert float(r[1, -1]) == 0.0  # NaN: not pinned
    torch.testing.assert_close(r[:, :-1], fit.residual(x, sel))
    free = torch.arange(fit.layout.num_scale_params)
    jac = pinned.jacobian(x, free, sel)
    assert float(jac[1, -1].abs().sum()) == 0.0
    h = 1e-6
    for p in free.tolist():
        plus, minus = x.clone(), x.clone()
        plus[:, p] += h
        minus[:, p] -= h
        fd = (pinned.residual(plus, sel)[0, -1] - pinned.residual(minus, sel)[0, -1]) / (2 * h)
        assert float(jac[0, -1, p]) == pytest.approx(float(fd), rel=1e-5, abs=1e-3)
    assert pinned.loss_units().shape == r.shape and bool(pinned.residual_mask()[:, -1].all())


@pytest.mark.slow
def test_pinning_what_the_images_show_costs_them(problem):
    stage, options = StageOptions(name="all"), LMOptions(max_iter=40)
    x, _ = solve_stage(problem, problem.initial_params(), stage, options)
    ratio = _span_ratio(problem)
    fitted = float(ratio(x, torch.arange(1))[0])
    fit = problem.subset([0, 0, 0])
    target = torch.tensor([fitted * 1.05, fitted, math.nan], dtype=torch.float64)
    cost, reached = pinning_cost(fit, x.expand(3, -1), stage, ratio, target, LMOptions(max_iter=20))
    assert float(reached[0]) == pytest.approx(fitted * 1.05, abs=0.01 * fitted)
    assert float(reached[1]) == pytest.approx(fitted, abs=1e-3)
    rise_off, rise_at = float(cost[0] - cost[2]), float(cost[1] - cost[2])
    assert rise_off > 2.0, (rise_off, rise_at)  # an arm span 5 % off the T-pose's
    assert abs(rise_at) < 0.2 * rise_off, (rise_off, rise_at)
    before = float(image_cost(problem, x, "linear", 1.0)[0])
    assert float(cost[2]) <= before + 1e-6  # the free refit does not make the images worse
