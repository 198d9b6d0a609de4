"""One iteration of the batched Levenberg–Marquardt solver on its active problems (the
method and its references: :func:`torchfit.solver.levenberg_marquardt`)."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchfit.solver.jacobians import ResidualFn, evaluate_residual
from torchfit.solver.normal import (
    Block,
    cholesky_each,
    cholesky_solve_each,
    normal_equations,
    valid_entries,
)
from torchfit.solver.options import LMOptions
from torchfit.solver.result import LMStatus
from torchfit.solver.robust import problem_cost, robust_correct
from torchfit.solver.steps import frozen_variables, geodesic_acceleration

__all__ = ["update_jacobian", "lm_step", "project"]

_BAD_NONFINITE = 1
_BAD_LINALG = 2


def project(v: torch.Tensor, lo: torch.Tensor | None, hi: torch.Tensor | None) -> torch.Tensor:
    """Clip ``v`` (B, P) into the bounds (None: unbounded on that side)."""
    if lo is not None:
        v = torch.maximum(v, lo)
    if hi is not None:
        v = torch.minimum(v, hi)
    return v


def update_jacobian(
    s: dict, jacobian_for: Callable, opts: LMOptions, blocks: list[Block] | None = None
) -> None:
    """Step 1 for the problems in the state ``s`` (all running) that need it; updates ``s``.

    ``jacobian_for(rows)`` gives the Jacobian routine ``(x, r, mask) -> J`` of the rows
    ``rows`` (positions in ``s``): the Jacobian is evaluated where a step was accepted (and
    at the start) only. ``blocks``: the Jacobian's sparsity, for the normal equations.
    """
    x, r, mask, cost, status = s["x"], s["r"], s.get("mask"), s["cost"], s["status"]
    lo, hi, fixed = s.get("lo"), s.get("hi"), s["fixed"]
    units, loss, scale = s.get("units"), opts.loss, opts.loss_scale
    has_bounds = lo is not None or hi is not None
    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    valid = valid_entries(mask, x.shape[0])
    diag2 = s["diag2"]

    # 1. Jacobian, normal equations, scaling and the gtol test after accepted steps; the
    # Jacobian is evaluated for those problems only.
    rows = s["need_jac"].nonzero()[:, 0]
    if rows.numel():
        every = rows.numel() == x.shape[0]
        pick = (lambda v: v) if every else (lambda v: v[rows])  # noqa: E731
        mask_u = None if mask is None else pick(mask)
        units_u = None if units is None else pick(units)
        valid_u = valid if every else [valid[i] for i in rows.tolist()]
        jac = jacobian_for(rows)(pick(x), pick(r), mask_u)
        r_u = pick(r)
        if isinstance(jac, tuple):  # a user Jacobian that also refreshes r at x
            jac, r_u = jac
            r = r.index_copy(0, rows, r_u)
            cost = cost.index_copy(0, rows, problem_cost(r_u, valid_u, loss, scale, units_u))
        s["njev"] = s["njev"].index_add(0, rows, torch.ones_like(rows))
        # Robust loss (torchfit.solver.robust): Triggs' correction of J and r, so that the
        # normal equations are those of 0.5 sum rho(r²); "linear" leaves them as they are.
        jac_w, r_w = robust_correct(jac, r_u, loss, scale, units_u)
        a_new, g_new = normal_equations(jac_w, r_w, valid_u, blocks)
        # J is finite where JᵀJ is (a non-finite entry of J makes its diagonal non-finite);
        # the exact test on J runs only where JᵀJ is not (it may also overflow for finite J).
        jac_ok = torch.isfinite(a_new.sum(dim=(1, 2)))
        if not bool(jac_ok.all()):
            jac_ok = torch.isfinite(jac).flatten(1).all(dim=1)
        status = status.index_copy(
            0, rows, torch.where(jac_ok, status[rows], int(LMStatus.NONFINITE))
        )
        rows, a_new, g_new = rows[jac_ok], a_new[jac_ok], g_new[jac_ok]
        s["a_mat"] = s["a_mat"].index_copy(0, rows, a_new)
        if "jac" in s:
            s["jac"] = s["jac"].index_copy(0, rows, jac[jac_ok])
        s["grad"] = s["grad"].index_copy(0, rows, g_new)
        col2 = torch.diagonal(a_new, dim1=1, dim2=2)
        # MINPACK mode 1: diag = max(diag, column norm); Ceres-style clamp of D².
        d_new = torch.maximum(diag2[rows], col2).clamp(opts.min_diag, opts.max_diag)
        diag2 = diag2.index_copy(0, rows, d_new)
        s["need_jac"] = torch.zeros_like(s["need_jac"])
        # gtol: max_j |J_jᵀ r| / (|J_j| |r|) over non-zero, free columns (MINPACK).
        rnorm = torch.sqrt(2 * cost[rows])
        counted = (col2 > 0) & (rnorm[:, None] > 0)
        if has_bounds:
            counted = counted & ~frozen_variables(
                x[rows], g_new, fixed[rows], _at(lo, rows), _at(hi, rows)
            )
        denom = torch.sqrt(col2) * rnorm[:, None]
        gnorm_u = torch.where(counted, g_new.abs() / denom, zero).amax(dim=1)
        s["gnorm"] = s["gnorm"].index_copy(0, rows, gnorm_u)
        status = status.index_copy(
            0, rows, torch.where(gnorm_u <= opts.gtol, int(LMStatus.GTOL), status[rows])
        )
        s.update(r=r, cost=cost, status=status, diag2=diag2)


def lm_step(s: dict, fn: ResidualFn, opts: LMOptions) -> tuple[torch.Tensor, torch.Tensor]:
    """Steps 2-5 for every problem in the state ``s`` (all running); updates ``s``.

    Returns:
        ``(step_norm, accepted)``, ``(N,)`` each.
    """
    x, r, mask, cost, status = s["x"], s["r"], s.get("mask"), s["cost"], s["status"]
    lo, hi, fixed = s.get("lo"), s.get("hi"), s["fixed"]
    has_bounds = lo is not None or hi is not None
    dtype, device = x.dtype, x.device
    eps = torch.finfo(dtype).eps
    zero = torch.zeros((), dtype=dtype, device=device)
    valid = valid_entries(mask, x.shape[0])
    mu, nu, diag2 = s["mu"], s["nu"], s["diag2"]
    running = status == LMStatus.RUNNING
    a_mat, grad, gnorm = s["a_mat"], s["grad"], s["gnorm"]

    # 2. Damped normal equations, rebuilt from the undamped A on every try.
    p = x.shape[1]
    eye = torch.eye(p, dtype=dtype, device=device)
    damped = a_mat + torch.diag_embed(mu[:, None] * diag2)
    rhs = -grad
    keep = None
    if has_bounds:
        keep = (~frozen_variables(x, grad, fixed, lo, hi)).to(dtype)
        damped = damped * keep[:, :, None] * keep[:, None, :] + torch.diag_embed(1 - keep)
        rhs = rhs * keep
    factor, info = cholesky_each(torch.where(running[:, None, None], damped, eye))
    h = cholesky_solve_each(rhs, factor)
    solved = running & (info == 0) & torch.isfinite(h).all(dim=1)
    h = torch.where(solved[:, None], h, zero)
    h_lm = h
    if opts.step_bound is not None:
        # MINPACK's step bound (its ``factor``): |D h| <= factor * |D x| (factor if x = 0).
        dnorm = torch.sqrt(diag2)
        bound = opts.step_bound * (dnorm * x).norm(dim=1)
        bound = torch.where(bound > 0, bound, torch.full_like(bound, opts.step_bound))
        dh = (dnorm * h).norm(dim=1)
        h = h * torch.where(dh > bound, bound / dh, torch.ones_like(dh))[:, None]
    too_curved = None
    nfev = s["nfev"]
    if "jac" in s:
        vel = h
        h, too_curved, n_fd = geodesic_acceleration(
            fn, x, r, mask, valid, s["jac"], factor, vel, diag2, keep, solved, opts
        )
        nfev = nfev + n_fd

    # 3. Trial point (projected) and gain ratio.
    x_new = x + h
    x_try = project(x_new, lo, hi) if has_bounds else x_new
    x_try = torch.where(solved[:, None], x_try, x)
    step = x_try - x
    r_try, mask_try = evaluate_residual(fn, x_try, r.shape[1])
    # A step rejected for its acceleration counts as not evaluated: no evaluation, no
    # convergence test, and not a bad step (it only raises the damping).
    tried = solved if too_curved is None else solved & ~too_curved
    nfev = nfev + tried.long()
    valid_try = valid_entries(mask_try, x.shape[0])
    cost_try = problem_cost(r_try, valid_try, opts.loss, opts.loss_scale, s.get("units"))
    finite = tried & torch.isfinite(cost_try)
    # The model's prediction is for the step taken or, with the acceleration, for the
    # velocity (where the bounds did not clip the step).
    step_pred = step
    if too_curved is not None:
        step_pred = torch.where((x_try != x_new).any(dim=1, keepdim=True), step, vel)
    clipped = (step_pred != h_lm).any(dim=1)
    s_as = (step_pred[:, :, None] * a_mat * step_pred[:, None, :]).sum(dim=(1, 2))
    g_s = (grad * step_pred).sum(dim=1)
    pred_general = -g_s - 0.5 * s_as
    # L(0) - L(h) = 0.5 hᵀ(mu D² h - g) for the unclipped step (Madsen et al. eq. 3.9b).
    pred_lm = 0.5 * ((mu[:, None] * diag2 * step_pred * step_pred).sum(dim=1) - g_s)
    pred = torch.where(clipped, pred_general, pred_lm)
    actual = cost - cost_try
    rho = torch.where(finite & (pred > 0), actual / pred, torch.full_like(pred, -1.0))
    accepted = finite & (rho > opts.accept_ratio)

    # 4. Nielsen's damping update; real rejection keeps x.
    shrink = torch.clamp(1 - (2 * rho - 1) ** 3, min=1.0 / 3.0)
    mu = torch.where(accepted, mu * shrink, torch.where(running, mu * nu, mu))
    nu = torch.where(accepted, torch.full_like(nu, 2.0), torch.where(running, nu * 2, nu))
    is_bad = running & ~finite if too_curved is None else running & ~(finite | too_curved)
    bad = s["bad"]
    bad = torch.where(is_bad, bad + 1, torch.where(running, torch.zeros_like(bad), bad))
    kind = torch.where(solved, _BAD_NONFINITE, _BAD_LINALG)
    bad_kind = torch.where(is_bad, kind, s["bad_kind"])
    cost_old = cost
    x = torch.where(accepted[:, None], x_try, x)
    r = torch.where(accepted[:, None], r_try, r)
    if mask is not None:
        s["mask"] = torch.where(accepted[:, None], mask_try, mask)
    cost = torch.where(accepted, cost_try, cost)
    s["need_jac"] = s["need_jac"] | accepted
    n_iter = s["n_iter"] + running.long()

    # 5. MINPACK's tests (lmder, info 1-8) on finite trials.
    pos = cost_old > 0
    safe_old = torch.where(pos, cost_old, torch.ones_like(cost_old))
    # MINPACK sets actred = -1 when the norm grew tenfold (cost a hundredfold).
    actred = torch.where(cost_try < 100 * cost_old, 1 - cost_try / safe_old, -1.0)
    actred = torch.where(pos, actred, zero)
    prered = torch.where(pos, pred / safe_old, zero)
    ratio_ok = 0.5 * rho <= 1
    dnorm = torch.sqrt(diag2)
    dxnorm = (dnorm * step).norm(dim=1)
    xnorm = (dnorm * x).norm(dim=1)
    c_f = finite & (actred.abs() <= opts.ftol) & (prered <= opts.ftol) & ratio_ok
    c_x = finite & (dxnorm <= opts.xtol * xnorm)
    new = torch.zeros_like(status)
    new = torch.where(c_x, LMStatus.XTOL, new)
    new = torch.where(c_f, LMStatus.FTOL, new)
    new = torch.where(c_f & c_x, LMStatus.FTOL_XTOL, new)
    fail = running & (bad >= opts.max_bad_steps)
    fail_code = torch.where(bad_kind == _BAD_LINALG, LMStatus.LINALG, LMStatus.NONFINITE)
    new = torch.where((new == 0) & fail, fail_code, new)
    limit = n_iter >= (s["max_iter"] if "max_iter" in s else opts.max_iter)
    if opts.max_nfev is not None:
        limit = limit | (nfev + s["n_free"] * s["njev"] >= opts.max_nfev)
    new = torch.where((new == 0) & limit, LMStatus.MAX_ITER, new)
    c6 = finite & (actred.abs() <= eps) & (prered <= eps) & ratio_ok
    c7 = finite & (dxnorm <= eps * xnorm)
    c8 = gnorm <= eps
    new = torch.where((new == 0) & c6, LMStatus.FTOL_TOO_SMALL, new)
    new = torch.where((new == 0) & c7, LMStatus.XTOL_TOO_SMALL, new)
    new = torch.where((new == 0) & c8, LMStatus.GTOL_TOO_SMALL, new)
    status = torch.where(running, new, status)
    s.update(x=x, r=r, cost=cost, status=status, mu=mu, nu=nu, bad=bad, bad_kind=bad_kind)
    s.update(n_iter=n_iter, nfev=nfev)
    return torch.where(running, step.norm(dim=1), zero), accepted


def _at(t: torch.Tensor | None, rows: torch.Tensor) -> torch.Tensor | None:
    return None if t is None else t[rows]
