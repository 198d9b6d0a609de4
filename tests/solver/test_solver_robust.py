"""Robust losses in the LM solver (torchfit.solver.robust): Triggs' correction against finite
differences of the robust cost, a line fit with outliers, NIST StRD unchanged with "linear"."""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import pytest
import torch

from torchfit.solver import LMOptions, SolverError, levenberg_marquardt
from torchfit.solver.robust import loss_rho, robust_correct, robust_cost

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_solver_nist import OPTIONS, _solve  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import nist_strd  # noqa: E402

DT = torch.float64


def _naive_rho(loss: str, s: float, a: float) -> float:
    """Ceres' loss functions (include/ceres/loss_function.h), one scalar at a time."""
    b = a * a
    if loss == "huber":
        return s if s <= b else 2 * math.sqrt(b * s) - b
    if loss == "cauchy":
        return b * math.log1p(s / b)
    return s


@pytest.mark.parametrize("loss", ["linear", "huber", "cauchy"])
def test_rho_and_its_derivatives_against_a_naive_loop(loss):
    s = torch.tensor([0.0, 0.3, 0.99, 1.0, 2.5, 40.0, 1e4], dtype=DT)
    a = 1.3
    rho0, rho1, rho2 = loss_rho(loss, s, a)
    expected = torch.tensor([_naive_rho(loss, float(v), a) for v in s], dtype=DT)
    torch.testing.assert_close(rho0, expected)
    # derivatives by central differences away from Huber's kink and s = 0
    h = 1e-6
    for i, v in enumerate(s.tolist()):
        if v < 0.1 or abs(v - a * a) < 0.1:
            continue
        d1 = (_naive_rho(loss, v + h, a) - _naive_rho(loss, v - h, a)) / (2 * h)
        assert float(rho1[i]) == pytest.approx(d1, rel=1e-6)
        d1p = float(loss_rho(loss, torch.tensor([v + h], dtype=DT), a)[1][0])
        d1m = float(loss_rho(loss, torch.tensor([v - h], dtype=DT), a)[1][0])
        assert float(rho2[i]) == pytest.approx((d1p - d1m) / (2 * h), rel=1e-5, abs=1e-12)


def test_infinite_scale_is_least_squares():
    s = torch.tensor([0.0, 1.0, 1e6], dtype=DT)
    for loss in ("huber", "cauchy"):
        rho0, rho1, rho2 = loss_rho(loss, s, torch.full_like(s, torch.inf))
        torch.testing.assert_close(rho0, s)
        torch.testing.assert_close(rho1, torch.ones_like(s))
        torch.testing.assert_close(rho2, torch.zeros_like(s))


def _model(theta: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    return theta[:, :1] * torch.exp(-theta[:, 1:2] * t) + theta[:, 2:3] * t


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_corrected_normal_equations_give_the_gradient_of_the_robust_cost(loss):
    """J̃ᵀr̃ is the gradient of ½Σρ(r²) (central differences in float64); with units."""
    torch.manual_seed(0)
    t = torch.linspace(0, 3, 17, dtype=DT)
    y = 2.0 * torch.exp(-0.7 * t) + 0.1 * t + torch.randn(17, dtype=DT) * 0.5
    y[[3, 9]] += 6.0  # entries far outside the scale
    units = torch.rand(1, 17, dtype=DT) + 0.5
    theta = torch.tensor([[1.5, 0.4, -0.2]], dtype=DT)

    def cost(th):
        return robust_cost(_model(th, t) - y, loss, 0.8, units)

    jac = torch.autograd.functional.jacobian(lambda th: _model(th, t)[0], theta)[:, 0, :]
    jac_w, r_w = robust_correct(jac[None], _model(theta, t) - y, loss, 0.8, units)
    grad = (jac_w.transpose(1, 2) @ r_w[:, :, None])[0, :, 0]
    h = 1e-6
    fd = torch.zeros(3, dtype=DT)
    for k in range(3):
        e = torch.zeros(1, 3, dtype=DT)
        e[0, k] = h
        fd[k] = (cost(theta + e) - cost(theta - e))[0] / (2 * h)
    torch.testing.assert_close(grad, fd, rtol=1e-6, atol=1e-8)


def test_second_order_correction_where_rho_is_convex():
    """Where ρ'' > 0 (a loss the library does not ship, checked through the formulas), the
    corrected J̃ᵀJ̃ is the exact Hessian along r, (ρ' + 2 s ρ'') JᵀJ (Triggs et al. eq. 11)."""
    from torchfit.solver import robust

    r = torch.tensor([[0.5, -2.0, 0.0]], dtype=DT)
    jac = torch.tensor([[[1.0], [2.0], [3.0]]], dtype=DT)
    s = r * r

    def convex(loss, s_, scale):  # ρ(s) = s + s²/4: ρ' = 1 + s/2, ρ'' = 1/2
        return s_ + s_ * s_ / 4, 1 + s_ / 2, torch.full_like(s_, 0.5)

    original = robust.loss_rho
    robust.loss_rho = convex
    try:
        jac_w, r_w = robust_correct(jac, r, "huber", 1.0)
    finally:
        robust.loss_rho = original
    rho1, rho2 = 1 + s / 2, 0.5
    torch.testing.assert_close(jac_w[0, :, 0] ** 2, (rho1 + 2 * s * rho2)[0] * jac[0, :, 0] ** 2)
    torch.testing.assert_close((jac_w[0, :, 0] * r_w[0]), (rho1 * r * jac[0, :, 0])[0])


def _line_problem(outlier_offset: float = 30.0):
    """y = 2 x + 1 with noise, 25 % of the points moved far off the line (a batch of 3)."""
    gen = torch.Generator().manual_seed(3)
    x = torch.linspace(-2, 2, 40, dtype=DT)
    y = 2 * x + 1 + 0.05 * torch.randn(40, generator=gen, dtype=DT)
    idx = torch.randperm(40, generator=gen)[:10]
    y[idx] += outlier_offset * (1 + torch.rand(10, generator=gen, dtype=DT))

    def residual(theta):
        return theta[:, :1] * x + theta[:, 1:2] - y

    return residual


@pytest.mark.parametrize("loss", ["linear", "huber", "cauchy"])
def test_line_fit_with_outliers(loss):
    """Huber and Cauchy recover the line through the outliers, least squares does not."""
    residual = _line_problem()
    x0 = torch.zeros(2, 2, dtype=DT)
    x0[1] = torch.tensor([1.0, -1.0])
    opts = LMOptions(loss=loss, loss_scale=0.2, max_iter=200, ftol=1e-12, xtol=1e-12)
    res = levenberg_marquardt(residual, x0, opts)
    error = (res.x - torch.tensor([2.0, 1.0], dtype=DT)).abs().amax(dim=1)
    if loss == "linear":
        assert bool((error > 1.0).all())
    else:
        assert bool((error < 0.1).all()), res.x
        rr = residual(res.x)
        torch.testing.assert_close(res.cost, robust_cost(rr, loss, 0.2))


def test_loss_units_make_the_scale_per_entry():
    """An entry scaled by 1/c with units 1/c is judged as the unscaled entry would be."""
    residual = _line_problem()
    c = torch.linspace(1.0, 5.0, 40, dtype=DT)
    x0 = torch.zeros(1, 2, dtype=DT)
    opts = LMOptions(loss="cauchy", loss_scale=0.2, max_iter=200, ftol=1e-12, xtol=1e-12)
    plain = levenberg_marquardt(residual, x0, opts)
    scaled = levenberg_marquardt(lambda th: residual(th) / c, x0, opts, loss_units=1 / c)
    # the scaled problem weighs entry i by 1/c_i² (the loss is homogeneous) but keeps the
    # outliers out: both find the line
    torch.testing.assert_close(scaled.x, plain.x, atol=0.05, rtol=0)
    with pytest.raises(SolverError, match="loss_units: expected shape"):
        levenberg_marquardt(residual, x0, opts, loss_units=torch.ones(3, dtype=DT))
    with pytest.raises(SolverError, match="loss_units: expected entries > 0"):
        levenberg_marquardt(residual, x0, opts, loss_units=torch.zeros(40, dtype=DT))


def test_options_reject_unknown_loss_and_bad_scale():
    with pytest.raises(SolverError, match="LMOptions.loss: expected one of"):
        LMOptions(loss="tukey")
    with pytest.raises(SolverError, match="LMOptions.loss_scale: expected a finite number > 0"):
        LMOptions(loss_scale=0.0)


def test_nist_start2_unchanged_with_linear_loss(shared_data):
    """Start 2 of all 27 NIST problems: loss="linear" spelled out gives the default's iterates
    exactly (the correction is skipped) and every parameter to LRE >= 4."""
    problems = nist_strd.load_all(shared_data / "nist-strd")
    starts = [p.start2 for p in problems]
    default, _ = _solve(problems, starts)
    linear, lre = _solve(problems, starts, dataclasses.replace(OPTIONS, loss="linear"))
    assert min(lre) >= 4
    torch.testing.assert_close(linear.x, default.x, rtol=0, atol=0)
    assert torch.equal(linear.n_iter, default.n_iter)
