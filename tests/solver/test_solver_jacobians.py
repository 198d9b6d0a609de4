"""Jacobians (forward, reverse, numeric, user callable) against a naive central-difference loop."""

from __future__ import annotations

import pytest
import torch

from torchfit.solver import (
    LMOptions,
    SolverError,
    jacobian_forward,
    jacobian_numeric,
    jacobian_reverse,
    levenberg_marquardt,
)

DATA = torch.linspace(0.0, 2.0, 7, dtype=torch.float64)


def residual(x: torch.Tensor) -> torch.Tensor:
    """(N, 3) -> (N, 7), written with in-place writes (as pytorch-kinematics does)."""
    out = torch.empty(x.shape[0], 7, dtype=x.dtype)
    out = out * 0  # a fresh buffer that in-place writes may then fill
    out[:, :] = x[:, :1] * torch.exp(-x[:, 1:2] * DATA) + torch.sin(x[:, 2:3] * DATA)
    out[:, 3] += x[:, 0] * x[:, 2]
    return out


def central_differences(fn, x: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    """Naive reference: one problem and one column at a time."""
    b, p = x.shape
    cols = torch.zeros(b, fn(x).shape[1], p, dtype=x.dtype)
    for i in range(b):
        for k in range(p):
            e = torch.zeros(p, dtype=x.dtype)
            e[k] = h
            up = fn((x[i] + e)[None])[0]
            down = fn((x[i] - e)[None])[0]
            cols[i, :, k] = (up - down) / (2 * h)
    return cols


X = torch.tensor([[1.0, 0.5, 0.3], [-2.0, 1.5, 2.0], [0.1, -0.3, 1.0]], dtype=torch.float64)


@pytest.mark.parametrize("fold", [True, False])
def test_autograd_jacobians_match_finite_differences(fold):
    ref = central_differences(residual, X)
    fwd = jacobian_forward(residual, X, 7, None, fold)
    rev = jacobian_reverse(residual, X, 7, None, fold)
    torch.testing.assert_close(fwd, ref, rtol=1e-7, atol=1e-8)
    torch.testing.assert_close(rev, fwd, rtol=1e-12, atol=1e-12)


def test_forward_mode_unfolds_large_batches(monkeypatch):
    # Where one copy of the batch holds FORWARD_UNFOLD_MIN_RESIDUALS residuals (B * M), forward
    # mode makes one call per tangent on (B, P) instead of one on (P*B, P): same Jacobian.
    from torchfit.solver import jacobians

    folded = jacobian_forward(residual, X, 7, None)
    rows = []

    def spy(v):
        rows.append(v.shape[0])
        return residual(v)

    monkeypatch.setattr(jacobians, "FORWARD_UNFOLD_MIN_RESIDUALS", 3 * 7)
    unfolded = jacobian_forward(spy, X, 7, None)
    assert rows == [3, 3, 3]
    torch.testing.assert_close(unfolded, folded, rtol=0, atol=0)
    rows.clear()
    monkeypatch.setattr(jacobians, "FORWARD_UNFOLD_MIN_RESIDUALS", 3 * 7 + 1)
    jacobian_forward(spy, X, 7, None)
    assert rows == [9]


@pytest.mark.parametrize("fold", [True, False])
def test_numeric_jacobian_matches_and_uses_the_documented_step(fold):
    r = residual(X)
    num = jacobian_numeric(residual, X, r, None, fold=fold)
    torch.testing.assert_close(num, central_differences(residual, X), rtol=1e-6, atol=1e-6)
    # The perturbed points are x + h e_k with h = sqrt(eps) * max(1, |x_k|).
    calls = []

    def spy(v):
        calls.append(v.clone())
        return residual(v)

    jacobian_numeric(spy, X, r, None, fold=fold)
    perturbed = torch.cat(calls).reshape(3, 3, 3)  # (P copies, B, P)
    h = torch.finfo(torch.float64).eps ** 0.5 * X.abs().clamp_min(1.0)
    for k in range(3):
        expected = X.clone()
        expected[:, k] += h[:, k]
        torch.testing.assert_close(perturbed[k], expected, rtol=0, atol=0)


def test_numeric_step_goes_backwards_at_the_upper_bound():
    calls = []

    def fn(v):
        calls.append(v.clone())
        return torch.sqrt(1.0 - v)  # undefined beyond the bound 1

    x = torch.tensor([[1.0]], dtype=torch.float64)
    jac = jacobian_numeric(fn, x, fn(x), None, upper=torch.ones(1, 1, dtype=torch.float64))
    assert calls[-1][0, 0] < 1.0 and torch.isfinite(jac).all()


def test_mask_zeroes_jacobian_rows():
    mask = torch.ones(3, 7, dtype=torch.bool)
    mask[1, 4:] = False
    jac = jacobian_forward(residual, X, 7, mask)
    assert (jac[1, 4:] == 0).all() and (jac[1, :4] != 0).any()


def test_user_callable_jacobian_and_its_shape_check():
    def jac(x):
        return central_differences(residual, x)

    target = residual(torch.tensor([[0.7, 0.2, 0.9]], dtype=torch.float64))

    def fit(x):
        return residual(x) - target

    x0 = torch.tensor([[1.0, 0.5, 0.5]], dtype=torch.float64)
    res = levenberg_marquardt(fit, x0, LMOptions(max_iter=100), jacobian=jac)
    torch.testing.assert_close(
        res.x, torch.tensor([[0.7, 0.2, 0.9]], dtype=torch.float64), rtol=0, atol=1e-6
    )
    with pytest.raises(SolverError, match=r"jacobian: expected shape \(1, 7, 3\), got \(1, 7\)"):
        levenberg_marquardt(fit, x0, jacobian=lambda x: torch.zeros(1, 7))


def test_autograd_picks_reverse_mode_when_p_exceeds_m():
    # P = 4 > M = 2: reverse mode; the solution is checked, not the mode.
    def fn(x):
        return torch.stack([x.sum(dim=1) - 1.0, (x * x).sum(dim=1) - 1.0], dim=1)

    x0 = torch.tensor([[0.9, 0.1, 0.2, 0.3]], dtype=torch.float64)
    res = levenberg_marquardt(fn, x0, LMOptions(max_iter=200, gtol=0.0))
    r = fn(res.x)
    torch.testing.assert_close(r, torch.zeros_like(r), rtol=0, atol=1e-8)


def test_folding_contract_error_names_the_fix():
    data = torch.ones(2, 4, dtype=torch.float64)

    def untiled(x):  # ignores the folding contract: data is not tiled
        return x[:, :1] * data - 1.0

    with pytest.raises(SolverError, match="fold_batch=False"):
        levenberg_marquardt(untiled, torch.zeros(2, 2, dtype=torch.float64))
    res = levenberg_marquardt(
        untiled, torch.zeros(2, 2, dtype=torch.float64), LMOptions(fold_batch=False)
    )
    torch.testing.assert_close(res.x[:, 0], torch.ones(2, dtype=torch.float64))
