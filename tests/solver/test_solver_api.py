"""Options, errors, masks, bounds, callback, statuses and the MINPACK baseline."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy.optimize import least_squares, leastsq

from torchfit.errors import TorchfitError
from torchfit.solver import (
    STATUS_MESSAGES,
    LMOptions,
    LMStatus,
    SolverError,
    levenberg_marquardt,
    minpack_baseline,
)

T = torch.linspace(0.0, 3.0, 12, dtype=torch.float64)
Y = 2.0 * torch.exp(-1.3 * T) + 0.5


def exp_residual(x: torch.Tensor) -> torch.Tensor:
    """(N, 3) -> (N, 12): a * exp(-k t) + c - y."""
    return x[:, :1] * torch.exp(-x[:, 1:2] * T) + x[:, 2:3] - Y


def test_import_does_not_load_tensorboard():
    code = (
        "import sys, torchfit.solver; "
        "print(any(m.startswith(('tensorboard', 'torch.utils.tensorboard')) for m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"max_iter": 0}, r"LMOptions.max_iter: expected >= 1, got 0"),
        ({"ftol": -1.0}, r"LMOptions.ftol: expected a finite number >= 0, got -1.0"),
        ({"initial_damping": 0.0}, r"LMOptions.initial_damping: expected a finite number > 0"),
        ({"min_diag": 1.0, "max_diag": 0.5}, r"LMOptions.min_diag: expected <= max_diag"),
        ({"step_bound": -1.0}, r"LMOptions.step_bound: expected None or a finite number > 0"),
        ({"max_bad_steps": 0}, r"LMOptions.max_bad_steps: expected >= 1, got 0"),
        ({"geodesic_acceleration": 1}, r"LMOptions.geodesic_acceleration: expected a bool"),
        ({"accel_ratio": 0.0}, r"LMOptions.accel_ratio: expected a finite number > 0"),
        ({"max_nfev": 0}, r"LMOptions.max_nfev: expected None or an int >= 1, got 0"),
        ({"max_nfev": 10.0}, r"LMOptions.max_nfev: expected None or an int >= 1, got 10.0"),
    ],
)
def test_bad_options_raise(kwargs, message):
    with pytest.raises(SolverError, match=message):
        LMOptions(**kwargs)
    assert issubclass(SolverError, TorchfitError)


def test_bad_inputs_raise_with_names():
    x0 = torch.ones(2, 3, dtype=torch.float64)
    with pytest.raises(
        SolverError, match=r"x0: expected a floating-point tensor of shape \(B, P\)"
    ):
        levenberg_marquardt(exp_residual, torch.ones(3, dtype=torch.float64))
    with pytest.raises(SolverError, match="x0: contains non-finite values"):
        levenberg_marquardt(exp_residual, torch.full((1, 3), float("nan"), dtype=torch.float64))
    with pytest.raises(SolverError, match=r"lower: expected shape \(3,\) or \(2, 3\), got \(4,\)"):
        levenberg_marquardt(exp_residual, x0, lower=torch.zeros(4))
    with pytest.raises(SolverError, match="lower: must be <= upper"):
        levenberg_marquardt(exp_residual, x0, lower=torch.ones(3), upper=torch.zeros(3))
    with pytest.raises(SolverError, match="jacobian: expected 'autograd'"):
        levenberg_marquardt(exp_residual, x0, jacobian="central")
    with pytest.raises(SolverError, match=r"residual_fn: expected residuals of shape \(2, M\)"):
        levenberg_marquardt(lambda x: x.sum(), x0)
    with pytest.raises(SolverError, match="the mask must be a bool tensor"):
        levenberg_marquardt(lambda x: (exp_residual(x), torch.ones(2, 12)), x0)
    with pytest.raises(SolverError, match="options: expected LMOptions"):
        levenberg_marquardt(exp_residual, x0, options={"max_iter": 3})


def test_matches_scipy_on_a_small_fit():
    x0 = torch.tensor([[1.0, 1.0, 0.0], [3.0, 0.5, 1.0]], dtype=torch.float64)
    res = levenberg_marquardt(exp_residual, x0, LMOptions(ftol=1e-12, xtol=1e-12, gtol=0.0))
    for b in range(2):
        ref = least_squares(
            lambda v: exp_residual(torch.from_numpy(v)[None])[0].numpy(),
            x0[b].numpy(),
            method="lm",
            xtol=1e-14,
            ftol=1e-14,
        )
        np.testing.assert_allclose(res.x[b].numpy(), ref.x, rtol=1e-8)
        assert float(res.cost[b]) == pytest.approx(ref.cost, abs=1e-20)
    assert res.success.all()
    assert res.message[0] == STATUS_MESSAGES[res.statuses[0]]


def test_mask_ignores_padding_even_if_it_holds_nan():
    # Problem 0 has 12 valid residuals, problem 1 only the first 7 (ragged data, padded to 12).
    valid = torch.ones(2, 12, dtype=torch.bool)
    valid[1, 7:] = False

    def padded(x):
        k = x.shape[0] // 2
        mask = valid.repeat(k, 1)
        r = exp_residual(x)
        return torch.where(mask, r, torch.nan), mask

    def short(x):
        return exp_residual(x)[:, :7]

    x0 = torch.tensor([[1.0, 1.0, 0.0], [1.5, 0.8, 0.2]], dtype=torch.float64)
    opts = LMOptions(ftol=1e-12, xtol=1e-12)
    res = levenberg_marquardt(padded, x0, opts)
    alone = levenberg_marquardt(short, x0[1:], opts)
    torch.testing.assert_close(res.x[1:], alone.x, rtol=1e-10, atol=0)
    torch.testing.assert_close(res.cost[1:], alone.cost, rtol=1e-10, atol=1e-30)
    assert torch.isfinite(res.cost).all() and res.success.all()


def test_bounds_match_scipy_trf():
    # The unconstrained fit has k = 1.3; bound k <= 1.0 and c >= 0.6 are active at the optimum.
    lower = torch.tensor([-torch.inf, -torch.inf, 0.6], dtype=torch.float64)
    upper = torch.tensor([torch.inf, 1.0, torch.inf], dtype=torch.float64)
    x0 = torch.tensor([[1.0, 0.5, 0.7]], dtype=torch.float64)
    res = levenberg_marquardt(
        exp_residual, x0, LMOptions(max_iter=300, ftol=1e-14, xtol=1e-14), lower=lower, upper=upper
    )
    ref = least_squares(
        lambda v: exp_residual(torch.from_numpy(v)[None])[0].numpy(),
        x0[0].numpy(),
        bounds=(lower.numpy(), upper.numpy()),
        method="trf",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
    )
    np.testing.assert_allclose(res.x[0].numpy(), ref.x, rtol=1e-6, atol=1e-9)
    assert float(res.x[0, 1]) == 1.0 and float(res.x[0, 2]) >= 0.6
    assert res.success.all()


def test_equal_bounds_fix_a_parameter():
    x0 = torch.tensor([[1.0, 2.0, 0.0]], dtype=torch.float64)
    lower = torch.tensor([-torch.inf, 2.0, -torch.inf], dtype=torch.float64)
    upper = torch.tensor([torch.inf, 2.0, torch.inf], dtype=torch.float64)
    res = levenberg_marquardt(exp_residual, x0, lower=lower, upper=upper)
    assert float(res.x[0, 1]) == 2.0
    # With k fixed the problem is linear in (a, c): compare with numpy's least squares.
    a_mat = torch.stack([torch.exp(-2.0 * T), torch.ones_like(T)], dim=1).numpy()
    sol, *_ = np.linalg.lstsq(a_mat, Y.numpy(), rcond=None)
    np.testing.assert_allclose(res.x[0, [0, 2]].numpy(), sol, rtol=1e-7)


def test_callback_values_and_stop():
    log = []

    def cb(it):
        log.append(it)
        return it.iteration == 3

    x0 = torch.tensor([[1.0, 1.0, 0.0], [3.0, 0.5, 1.0]], dtype=torch.float64)
    res = levenberg_marquardt(exp_residual, x0, callback=cb)
    assert [it.iteration for it in log] == [1, 2, 3]
    assert res.statuses == [LMStatus.STOPPED, LMStatus.STOPPED]
    last = log[-1]
    torch.testing.assert_close(last.x, res.x)
    torch.testing.assert_close(last.cost, 0.5 * (exp_residual(res.x) ** 2).sum(dim=1))
    assert last.step_norm.shape == (2,) and last.accepted.dtype == torch.bool
    assert not last.x.requires_grad


def test_max_iter_and_gtol_statuses():
    x0 = torch.tensor([[1.0, 1.0, 0.0]], dtype=torch.float64)
    res = levenberg_marquardt(exp_residual, x0, LMOptions(max_iter=2))
    assert res.statuses == [LMStatus.MAX_ITER] and int(res.n_iter[0]) == 2
    assert res.message == [
        "number of iterations reached max_iter (or residual evaluations max_nfev)"
    ]
    # Already at a zero-residual optimum: the gradient test stops before any step.
    exact = torch.tensor([[2.0, 1.3, 0.5]], dtype=torch.float64)
    res = levenberg_marquardt(exp_residual, exact, LMOptions(gtol=1e-8))
    assert res.statuses == [LMStatus.GTOL] and int(res.n_iter[0]) == 0


def test_float32_runs():
    x0 = torch.tensor([[1.0, 1.0, 0.0]], dtype=torch.float32)

    def fn(x):
        return x[:, :1] * torch.exp(-x[:, 1:2] * T.float()) + x[:, 2:3] - Y.float()

    res = levenberg_marquardt(fn, x0)
    assert res.x.dtype == torch.float32
    torch.testing.assert_close(res.x[0], torch.tensor([2.0, 1.3, 0.5]), rtol=1e-3, atol=1e-3)


def test_minpack_baseline_is_leastsq():
    x0 = torch.tensor([[1.0, 1.0, 0.0], [3.0, 0.5, 1.0]], dtype=torch.float64)
    opts = LMOptions(ftol=1e-10, xtol=1e-10, gtol=0.0)
    base = minpack_baseline(exp_residual, x0, opts)
    for b in range(2):
        sol, _, info, _, ier = leastsq(
            lambda v: exp_residual(torch.from_numpy(v)[None])[0].numpy(),
            x0[b].numpy(),
            full_output=True,
            ftol=1e-10,
            xtol=1e-10,
            gtol=0.0,
            maxfev=opts.max_iter * 4,
        )
        np.testing.assert_array_equal(base.x[b].numpy(), sol)
        assert int(base.status[b]) == ier and int(base.nfev[b]) == info["nfev"]
    assert base.success.all()
    ours = levenberg_marquardt(exp_residual, x0, opts)
    torch.testing.assert_close(ours.x, base.x, rtol=1e-7, atol=0)


def test_solver_config_mirrors_lm_options():
    import dataclasses

    from torchfit.config import SolverConfig

    cfg = {f.name: getattr(SolverConfig(), f.name) for f in dataclasses.fields(SolverConfig)}
    opts = {f.name: getattr(LMOptions(), f.name) for f in dataclasses.fields(LMOptions)}
    assert cfg.pop("jacobian") == "autograd"
    # the fit's own defaults: Huber at 3 px, tolerances 1e-6 and a floor of 1 under the
    # scaling (the solver's stay least squares, 1e-8 and 1e-12, for other problems)
    assert (cfg.pop("loss"), cfg.pop("loss_scale")) == ("huber", 3.0)
    assert (opts.pop("loss"), opts.pop("loss_scale")) == ("linear", 1.0)
    assert (cfg.pop("ftol"), cfg.pop("xtol"), cfg.pop("min_diag")) == (1e-6, 1e-6, 1.0)
    assert (opts.pop("ftol"), opts.pop("xtol"), opts.pop("min_diag")) == (1e-8, 1e-8, 1e-12)
    assert cfg == opts
    # The pipeline's conversion carries every field, and a stage's own limit.
    custom = SolverConfig(
        ftol=1e-3, max_bad_steps=3, geodesic_acceleration=True, max_nfev=50, loss="cauchy"
    )
    assert custom.lm_options(7) == LMOptions(
        max_iter=7,
        ftol=1e-3,
        max_bad_steps=3,
        geodesic_acceleration=True,
        max_nfev=50,
        loss="cauchy",
        loss_scale=3.0,
        xtol=1e-6,
        min_diag=1.0,
    )


def test_step_bound_limits_a_long_first_step():
    def fn(x):
        return 1e-3 * (x - 1e6)

    x0 = torch.ones(1, 1, dtype=torch.float64)
    log = []
    levenberg_marquardt(fn, x0, LMOptions(max_iter=1, initial_damping=1e-9), callback=log.append)
    # |D h| <= 100 |D x| with one parameter: the step is at most 100 * |x0|.
    torch.testing.assert_close(log[0].x, torch.full((1, 1), 101.0, dtype=torch.float64))
    log.clear()
    opts = LMOptions(max_iter=1, initial_damping=1e-9, step_bound=None)
    levenberg_marquardt(fn, x0, opts, callback=log.append)
    assert float(log[0].x) == pytest.approx(1e6, rel=1e-6)


def test_max_nfev_counts_evaluations_as_lmdif():
    # P = 3 free parameters: the start costs 1 evaluation, each Jacobian 3, each trial 1.
    x0 = torch.tensor([[1.0, 1.0, 0.0]], dtype=torch.float64)
    res = levenberg_marquardt(exp_residual, x0, LMOptions(max_nfev=12, gtol=0.0))
    spent = int(res.nfev[0]) + 3 * int(res.njev[0])
    assert res.statuses == [LMStatus.MAX_ITER] and 12 <= spent < 12 + 3 + 1
    # A parameter held by equal bounds is not free: its Jacobian column costs nothing.
    lower = torch.tensor([-torch.inf, -torch.inf, 0.0], dtype=torch.float64)
    upper = torch.tensor([torch.inf, torch.inf, 0.0], dtype=torch.float64)
    res = levenberg_marquardt(
        exp_residual, x0, LMOptions(max_nfev=12, gtol=0.0), lower=lower, upper=upper
    )
    spent = int(res.nfev[0]) + 2 * int(res.njev[0])
    assert res.statuses == [LMStatus.MAX_ITER] and 12 <= spent < 12 + 2 + 1
    # MINPACK gets the same budget from the same options.
    base = minpack_baseline(exp_residual, x0, LMOptions(max_nfev=12, gtol=0.0))
    assert base.statuses == [LMStatus.MAX_ITER] and int(base.nfev[0]) >= 12


def test_geodesic_acceleration_first_step_by_hand():
    # r(x) = (x0² - 2, x0 x1 - 1, x1 - 0.5): quadratic, so the finite difference along v gives
    # the exact second directional derivative r_vv = (2 v0², 2 v0 v1, 0).
    def fn(x):
        return torch.stack([x[:, 0] ** 2 - 2, x[:, 0] * x[:, 1] - 1, x[:, 1] - 0.5], dim=1)

    x0 = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    opts = LMOptions(max_iter=1, geodesic_acceleration=True, accel_ratio=10.0, step_bound=None)
    log = []
    res = levenberg_marquardt(fn, x0, opts, callback=log.append)
    x, r = x0[0], fn(x0)[0]
    jac = torch.tensor([[2 * x[0], 0.0], [x[1], x[0]], [0.0, 1.0]], dtype=torch.float64)
    a_mat = jac.T @ jac
    damped = a_mat + opts.initial_damping * torch.diag(torch.diagonal(a_mat))
    v = torch.linalg.solve(damped, -jac.T @ r)
    rvv = torch.stack([2 * v[0] ** 2, 2 * v[0] * v[1], torch.zeros((), dtype=torch.float64)])
    a = torch.linalg.solve(damped, -jac.T @ rvv)
    assert bool(log[0].accepted[0])
    torch.testing.assert_close(res.x[0], x + v + 0.5 * a, rtol=1e-9, atol=0)
    assert int(res.nfev[0]) == 3  # start, acceleration probe, trial
    # A step with |D a| > accel_ratio |D v| is rejected without evaluating it.
    strict = LMOptions(max_iter=1, geodesic_acceleration=True, accel_ratio=1e-6, step_bound=None)
    res = levenberg_marquardt(fn, x0, strict)
    torch.testing.assert_close(res.x, x0)
    assert int(res.nfev[0]) == 2 and float(res.damping[0]) == 2 * opts.initial_damping


def test_keep_heap_sets_glibc_thresholds_in_a_fresh_process():
    # In a subprocess, so the test run keeps its own allocator settings. The solve after it
    # must give the same answer as here: the setting changes memory reuse only.
    from torchfit.solver import keep_heap

    with pytest.raises(ValueError, match="mmap_threshold=0"):
        keep_heap(mmap_threshold=0)
    code = (
        "import platform, torch; from torchfit.solver import keep_heap, levenberg_marquardt; "
        "t = torch.linspace(0.0, 3.0, 12, dtype=torch.float64); "
        "y = 2.0 * torch.exp(-1.3 * t) + 0.5; "
        "f = lambda x: x[:, :1] * torch.exp(-x[:, 1:2] * t) + x[:, 2:3] - y; "
        "ok = keep_heap(); "
        "x = levenberg_marquardt(f, torch.tensor([[1.0, 1.0, 0.0]], dtype=torch.float64)).x; "
        "print(ok, platform.libc_ver()[0] == 'glibc', *x[0].tolist())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    ok, glibc, *x = out.stdout.split()
    assert ok == glibc  # set exactly where the C library is glibc
    x0 = torch.tensor([[1.0, 1.0, 0.0]], dtype=torch.float64)
    expected = levenberg_marquardt(exp_residual, x0).x[0]
    assert torch.equal(torch.tensor([float(v) for v in x], dtype=torch.float64), expected)


def test_min_diag_damps_a_parameter_the_data_barely_sees():
    # x1 barely moves the data term (its column is 1e-4 times x0's) and a barrier that is flat
    # inside [-1, 1] holds it: a body joint the camera cannot see, held by its interval. With
    # Marquardt's scaling alone its damping is ~0, the first trial steps are thousands of units
    # long and rejected, and the solve ends falsely far from the answer (x0 = 2); a floor under
    # diag(JᵀJ) damps it and the problem is solved.
    def residual(x: torch.Tensor) -> torch.Tensor:
        data = 3 * (x[:, 0] - 2 + 1e-4 * x[:, 1])
        barrier = 100 * torch.relu(x[:, 1].abs() - 1)
        return torch.stack([data, barrier, 0.1 * x[:, 0] - 0.2], dim=1)

    x0 = torch.tensor([[0.5, 0.2]], dtype=torch.float64)
    runs = {}
    for min_diag in (1e-12, 1.0):
        log = []
        res = levenberg_marquardt(
            residual,
            x0,
            LMOptions(max_iter=50, min_diag=min_diag),
            callback=lambda it, log=log: log.append((float(it.step_norm[0]), bool(it.accepted[0]))),
        )
        runs[min_diag] = res, log
    res, log = runs[1e-12]
    assert log[0][0] > 1000 and not log[0][1]  # a huge first step, rejected
    assert float(res.cost[0]) > 1.0 and abs(float(res.x[0, 0]) - 2) > 1  # stopped far off
    res, log = runs[1.0]
    assert log[0][1] and log[0][0] < 2  # a sensible first step, accepted
    assert float(res.cost[0]) < 1e-20 and abs(float(res.x[0, 0]) - 2) < 1e-9
