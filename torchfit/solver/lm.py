"""Batched Levenberg–Marquardt with per-problem damping, acceptance, convergence and failure.

Each of the ``B`` problems minimises ``F(x) = 0.5 * |r(x)|²`` on its own: every piece of state
(damping, scaling, counters, status) is a ``(B,)`` or ``(B, P)`` tensor and no problem's value
depends on another's, so a batch gives the iterates of each problem solved alone.

One iteration, for every running problem (references in brackets):

1. After an accepted step (and at the start): the Jacobian ``J``, ``A = JᵀJ``, ``g = Jᵀr`` and
   Marquardt's scaling ``D² = diag(JᵀJ)`` [Marquardt 1963], kept non-decreasing as MINPACK's
   ``mode = 1`` does and clamped to ``[min_diag, max_diag]`` [Moré 1978; Ceres Solver's
   ``min_lm_diagonal`` / ``max_lm_diagonal``]; then the ``gtol`` test.
2. Solve ``(A + mu D²) h = -g`` by Cholesky (``torch.linalg.cholesky_ex``). The damped matrix
   is rebuilt from the undamped ``A`` on every try. A failed factorisation counts as a bad step.
   With ``geodesic_acceleration``, ``h`` is the velocity ``v`` of a second-order step
   ``v + a/2`` (see below).
3. Project ``x + h`` onto the bounds, evaluate the residual there (one evaluation) and form the
   gain ratio ``rho = (F(x) - F(x_new)) / (L(0) - L(h))`` with the Gauss–Newton model ``L``
   (``L(v)`` with the geodesic acceleration). A non-finite trial residual counts as a bad step.
4. Accept when ``rho > accept_ratio`` (x, r and cost move to the trial point); otherwise the
   trial is rejected and x is kept. Damping follows Nielsen: on acceptance
   ``mu *= max(1/3, 1 - (2 rho - 1)³)``, ``nu = 2``; on rejection or a bad step ``mu *= nu``,
   ``nu *= 2`` [Nielsen 1999; Madsen, Nielsen & Tingleff 2004, eq. 3.16]. ``max_bad_steps``
   consecutive bad steps fail the problem.
5. MINPACK's convergence tests (``lmder``: info 1–8) [Moré, Garbow & Hillstrom 1980]; the
   limits ``max_iter`` (trial steps) and ``max_nfev`` (residual evaluations, a Jacobian counting
   one per free parameter as ``lmdif``'s forward differences) give info 5.

Geodesic acceleration (``LMOptions.geodesic_acceleration``) [Transtrum, Machta & Sethna 2011;
Transtrum & Sethna 2012]: the LM step ``v`` is the first-order term of a geodesic on the model
manifold; the second-order term ``a = -(A + mu D²)⁻¹ Jᵀ r_vv`` uses the second directional
derivative ``r_vv`` of the residual along ``v``, by the finite difference
``r_vv ≈ (2/t) ((r(x + t v) - r(x)) / t - J v)`` with ``t = 0.1`` (one more evaluation per trial;
the Cholesky factor is reused). The trial step is ``v + a/2``; one whose scaled acceleration is
large, ``|D a| > accel_ratio |D v|``, leaves the quadratic model's region of validity and is
rejected without evaluating it (the damping grows as on any rejection). The gain ratio
compares the actual reduction with the Gauss–Newton prediction for ``v``: the acceleration
corrects the step along the path that prediction is for. It lets the method follow narrow
curved valleys with longer steps and keeps steps from running onto plateaus where parameters
"evaporate" (an exponential rate running off to infinity, as BoxBOD from NIST's Start 1).

Bounds (optional) are handled by projection: a trial point is clipped to ``[lower, upper]``,
and a variable that sits on a bound with the gradient pointing out of the box (or whose bounds
are equal) is held fixed for that step [cf. Kanzow, Yamashita & Fukushima 2004, projected LM].
The gain ratio uses the step actually taken.

References:
    D. W. Marquardt, "An algorithm for least-squares estimation of nonlinear parameters",
    SIAM J. Appl. Math. 11(2), 1963.
    J. J. Moré, "The Levenberg–Marquardt algorithm: implementation and theory", Lecture Notes
    in Mathematics 630, 1978.
    J. J. Moré, B. S. Garbow, K. E. Hillstrom, "User Guide for MINPACK-1", ANL-80-74, 1980.
    H. B. Nielsen, "Damping parameter in Marquardt's method", IMM-REP-1999-05, DTU, 1999.
    K. Madsen, H. B. Nielsen, O. Tingleff, "Methods for non-linear least squares problems",
    2nd ed., DTU, 2004.
    M. K. Transtrum, B. B. Machta, J. P. Sethna, "Geometry of nonlinear least squares with
    applications to sloppy models and optimization", Phys. Rev. E 83, 036701, 2011.
    M. K. Transtrum, J. P. Sethna, "Improvements to the Levenberg–Marquardt algorithm for
    nonlinear least-squares minimization", arXiv:1201.5885, 2012.
    C. Kanzow, N. Yamashita, M. Fukushima, "Levenberg–Marquardt methods with strong local
    convergence properties for solving nonlinear equations with convex constraints",
    J. Comput. Appl. Math. 172, 2004.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchfit.solver.jacobians import JacobianFn, ResidualFn, evaluate_residual, make_jacobian
from torchfit.solver.options import LMOptions, SolverError
from torchfit.solver.result import LMIterate, LMResult, LMStatus
from torchfit.solver.robust import check_loss_units, robust_correct, robust_cost

__all__ = ["levenberg_marquardt"]

Callback = Callable[[LMIterate], "bool | None"]

_BAD_NONFINITE = 1
_BAD_LINALG = 2
# Finite-difference step t along the velocity for the second directional derivative of the
# geodesic acceleration (Transtrum & Sethna 2012, section IV: t = 0.1).
_ACCEL_FD_STEP = 0.1


def _check_bound(name: str, bound: torch.Tensor | None, x0: torch.Tensor) -> torch.Tensor | None:
    if bound is None:
        return None
    if not isinstance(bound, torch.Tensor):
        bound = torch.as_tensor(bound, dtype=x0.dtype, device=x0.device)
    b, p = x0.shape
    if tuple(bound.shape) not in ((p,), (b, p)):
        raise SolverError(f"{name}: expected shape ({p},) or ({b}, {p}), got {tuple(bound.shape)}")
    if torch.isnan(bound).any():
        raise SolverError(f"{name}: contains NaN")
    return bound.to(dtype=x0.dtype, device=x0.device).expand(b, p)


def levenberg_marquardt(
    residual_fn: ResidualFn,
    x0: torch.Tensor,
    options: LMOptions | None = None,
    jacobian: str | JacobianFn = "autograd",
    callback: Callback | None = None,
    lower: torch.Tensor | None = None,
    upper: torch.Tensor | None = None,
    loss_units: torch.Tensor | None = None,
) -> LMResult:
    """Solve ``B`` independent nonlinear least-squares problems ``min_x 0.5 |r_b(x)|²``.

    Args:
        residual_fn: ``x (N, P) -> r (N, M)``, or ``-> (r, mask)`` with ``mask`` a ``(N, M)``
            bool tensor (``False`` entries are padding and count as zero in the cost and the
            Jacobian). Rows must be independent: row ``i`` of the output depends on row ``i``
            of the input only. ``N`` is ``B``, or ``K * B`` when a Jacobian is evaluated on
            ``K`` stacked copies of the batch (row ``i`` belongs to problem ``i % B``; see
            :attr:`LMOptions.fold_batch`). For ``jacobian="autograd"`` it must be built from
            differentiable torch operations (forward mode needs forward-AD support); it is
            never run under ``torch.func.vmap``.
        x0: ``(B, P)`` floating-point start; its dtype and device are used throughout
            (float64 recommended). Clipped into the bounds.
        options: tolerances and limits, the same for every problem (default ``LMOptions()``).
        jacobian: ``"autograd"`` (forward mode when ``P <= M``, else reverse mode),
            ``"forward"``, ``"reverse"``, ``"numeric"`` (forward differences,
            ``h = sqrt(eps) * max(1, |x|)``) or a callable ``x (B, P) -> J (B, M, P)``. The
            callable may return ``(J, r)`` to refresh the residual at ``x`` as well: each
            trial step is then judged against the residual of the last refresh, which lets
            a problem redefine its residual (re-associate data) after every accepted step.
        callback: called after every iteration with an :class:`LMIterate` of detached values;
            returning ``True`` stops every running problem with status ``STOPPED``.
        lower, upper: optional bounds, ``(P,)`` or ``(B, P)``, ``±inf`` for none. Handled by
            projection (see the module docstring); ``lower == upper`` fixes a parameter.
        loss_units: optional ``(M,)`` or ``(B, M)`` size of one unit of
            :attr:`LMOptions.loss_scale` in each residual entry (``inf``: that entry stays least
            squares whatever :attr:`LMOptions.loss`); see :mod:`torchfit.solver.robust`.

    Returns:
        :class:`LMResult` with ``x (B, P)``, ``cost (B,)``, ``status (B,)`` and counters.

    Raises:
        SolverError: for bad shapes, dtypes, bounds, options, a ``jacobian`` argument it does
            not know, or a residual/Jacobian function returning the wrong shape.
    """
    opts = options if options is not None else LMOptions()
    if not isinstance(opts, LMOptions):
        raise SolverError(f"options: expected LMOptions, got {type(opts).__name__}")
    if not isinstance(x0, torch.Tensor) or x0.dim() != 2 or not x0.is_floating_point():
        got = f"{tuple(x0.shape)} {x0.dtype}" if isinstance(x0, torch.Tensor) else type(x0).__name__
        raise SolverError(f"x0: expected a floating-point tensor of shape (B, P), got {got}")
    if x0.shape[0] == 0 or x0.shape[1] == 0:
        raise SolverError(f"x0: expected B >= 1 and P >= 1, got shape {tuple(x0.shape)}")
    if not torch.isfinite(x0).all():
        raise SolverError("x0: contains non-finite values")
    lo = _check_bound("lower", lower, x0)
    hi = _check_bound("upper", upper, x0)
    if lo is not None and hi is not None and (lo > hi).any():
        raise SolverError("lower: must be <= upper everywhere")

    dtype, device = x0.dtype, x0.device
    bsz, p = x0.shape
    eps = torch.finfo(dtype).eps

    def project(v: torch.Tensor) -> torch.Tensor:
        if lo is not None:
            v = torch.maximum(v, lo)
        if hi is not None:
            v = torch.minimum(v, hi)
        return v

    has_bounds = lo is not None or hi is not None
    accel = opts.geodesic_acceleration
    fixed = torch.zeros(bsz, p, dtype=torch.bool, device=device)
    if lo is not None and hi is not None:
        fixed = lo == hi

    with torch.no_grad():
        x = project(x0.detach().clone())
        r, mask = evaluate_residual(residual_fn, x)
        if r.dtype != dtype:
            raise SolverError(f"residual_fn: expected dtype {dtype} (that of x0), got {r.dtype}")
        m = r.shape[1]
        jac_fn = make_jacobian(jacobian, residual_fn, p, m, hi, opts.fold_batch)

        units = check_loss_units(loss_units, r)

        def cost_of(res: torch.Tensor) -> torch.Tensor:
            return robust_cost(res, opts.loss, opts.loss_scale, units)

        cost = cost_of(r)
        status = torch.zeros(bsz, dtype=torch.long, device=device)
        status[~torch.isfinite(cost)] = LMStatus.NONFINITE
        mu = torch.full((bsz,), opts.initial_damping, dtype=dtype, device=device)
        nu = torch.full((bsz,), 2.0, dtype=dtype, device=device)
        diag2 = torch.zeros(bsz, p, dtype=dtype, device=device)
        a_mat = torch.zeros(bsz, p, p, dtype=dtype, device=device)
        # The Jacobian of the last update (kept for J v in the geodesic acceleration only).
        jac_cur = torch.zeros(bsz, m, p, dtype=dtype, device=device) if accel else None
        # Free parameters per problem: what a Jacobian costs in evaluations for max_nfev.
        n_free = (~fixed).sum(dim=1)
        grad = torch.zeros(bsz, p, dtype=dtype, device=device)
        gnorm = torch.zeros(bsz, dtype=dtype, device=device)
        need_jac = torch.ones(bsz, dtype=torch.bool, device=device)
        n_iter = torch.zeros(bsz, dtype=torch.long, device=device)
        nfev = torch.ones(bsz, dtype=torch.long, device=device)
        njev = torch.zeros(bsz, dtype=torch.long, device=device)
        bad = torch.zeros(bsz, dtype=torch.long, device=device)
        bad_kind = torch.zeros(bsz, dtype=torch.long, device=device)
        zero = torch.zeros((), dtype=dtype, device=device)
        eye = torch.eye(p, dtype=dtype, device=device)
        iteration = 0

        while True:
            running = status == LMStatus.RUNNING
            if not bool(running.any()):
                break
            iteration += 1

            # 1. Jacobian, normal equations, scaling and the gtol test after accepted steps.
            upd = running & need_jac
            if bool(upd.any()):
                jac = jac_fn(x, r, mask)
                if isinstance(jac, tuple):  # a user Jacobian that also refreshes r at x
                    jac, r_new = jac
                    r = torch.where(upd[:, None], r_new, r)
                    cost = torch.where(upd, cost_of(r_new), cost)
                njev += upd.long()
                # Rows not updated are computed too (and then not selected): a row of the
                # batched products depends on that row of J only. The built-in Jacobians are
                # (B, M, P) views of (B, P, M) storage, the fast layout for these products.
                # Robust loss (torchfit.solver.robust): Triggs' correction of J and r, so that
                # the normal equations are those of 0.5 sum rho(r²); "linear" leaves them as is.
                jac_w, r_w = robust_correct(jac, r, opts.loss, opts.loss_scale, units)
                jac_t = jac_w.transpose(1, 2)
                a_new = jac_t @ jac_w
                g_new = (jac_t @ r_w[:, :, None])[:, :, 0]
                # J is finite where JᵀJ is (a non-finite entry of J makes its diagonal
                # non-finite); the exact test on J runs only where JᵀJ is not (it may also
                # overflow for finite J).
                jac_ok = torch.isfinite(a_new.sum(dim=(1, 2)))
                if not bool(jac_ok.all()):
                    jac_ok = torch.isfinite(jac).flatten(1).all(dim=1)
                status = torch.where(upd & ~jac_ok, int(LMStatus.NONFINITE), status)
                upd = upd & jac_ok
                sel = upd[:, None]
                a_mat = torch.where(sel[:, :, None], a_new, a_mat)
                if jac_cur is not None:
                    jac_cur = torch.where(sel[:, :, None], jac, jac_cur)
                grad = torch.where(sel, g_new, grad)
                col2 = torch.diagonal(a_new, dim1=1, dim2=2)
                # MINPACK mode 1: diag = max(diag, column norm); Ceres-style clamp of D².
                d_new = torch.maximum(diag2, col2).clamp(opts.min_diag, opts.max_diag)
                diag2 = torch.where(sel, d_new, diag2)
                need_jac = need_jac & ~upd
                # gtol: max_j |J_jᵀ r| / (|J_j| |r|) over non-zero, free columns (MINPACK).
                rnorm = torch.sqrt(2 * cost)
                counted = (col2 > 0) & (rnorm[:, None] > 0)
                if has_bounds:
                    counted = counted & ~_frozen(x, g_new, fixed, lo, hi)
                denom = torch.sqrt(col2) * rnorm[:, None]
                cosines = torch.where(counted, g_new.abs() / denom, zero)
                gnorm = torch.where(upd, cosines.amax(dim=1), gnorm)
                status = torch.where(upd & (gnorm <= opts.gtol), int(LMStatus.GTOL), status)
                running = status == LMStatus.RUNNING
                if not bool(running.any()):
                    break

            # 2. Damped normal equations, rebuilt from the undamped A on every try.
            damped = a_mat + torch.diag_embed(mu[:, None] * diag2)
            rhs = -grad
            keep = None
            if has_bounds:
                keep = (~_frozen(x, grad, fixed, lo, hi)).to(dtype)
                damped = damped * keep[:, :, None] * keep[:, None, :] + torch.diag_embed(1 - keep)
                rhs = rhs * keep
            factor, info = torch.linalg.cholesky_ex(
                torch.where(running[:, None, None], damped, eye)
            )
            h = torch.cholesky_solve(rhs[:, :, None], factor)[:, :, 0]
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
            if accel:
                vel = h
                h, too_curved, n_fd = _geodesic_acceleration(
                    residual_fn, x, r, mask, jac_cur, factor, vel, diag2, keep, solved, opts
                )
                nfev += n_fd

            # 3. Trial point (projected) and gain ratio.
            x_new = x + h
            x_try = project(x_new) if has_bounds else x_new
            x_try = torch.where(solved[:, None], x_try, x)
            step = x_try - x
            r_try, mask_try = evaluate_residual(residual_fn, x_try, m)
            # A step rejected for its acceleration counts as not evaluated: no evaluation, no
            # convergence test, and not a bad step (it only raises the damping).
            tried = solved if too_curved is None else solved & ~too_curved
            nfev += tried.long()
            cost_try = cost_of(r_try)
            finite = tried & torch.isfinite(cost_try)
            # The model's prediction is for the step taken or, with the acceleration, for the
            # velocity (where the bounds did not clip the step).
            step_pred = step
            if accel:
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
            bad = torch.where(is_bad, bad + 1, torch.where(running, torch.zeros_like(bad), bad))
            kind = torch.where(solved, _BAD_NONFINITE, _BAD_LINALG)
            bad_kind = torch.where(is_bad, kind, bad_kind)
            cost_old = cost
            x = torch.where(accepted[:, None], x_try, x)
            r = torch.where(accepted[:, None], r_try, r)
            if mask is not None:
                mask = torch.where(accepted[:, None], mask_try, mask)
            cost = torch.where(accepted, cost_try, cost)
            need_jac = need_jac | accepted
            n_iter += running.long()

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
            limit = n_iter >= opts.max_iter
            if opts.max_nfev is not None:
                limit = limit | (nfev + n_free * njev >= opts.max_nfev)
            new = torch.where((new == 0) & limit, LMStatus.MAX_ITER, new)
            c6 = finite & (actred.abs() <= eps) & (prered <= eps) & ratio_ok
            c7 = finite & (dxnorm <= eps * xnorm)
            c8 = gnorm <= eps
            new = torch.where((new == 0) & c6, LMStatus.FTOL_TOO_SMALL, new)
            new = torch.where((new == 0) & c7, LMStatus.XTOL_TOO_SMALL, new)
            new = torch.where((new == 0) & c8, LMStatus.GTOL_TOO_SMALL, new)
            status = torch.where(running, new, status)

            if callback is not None:
                record = LMIterate(
                    iteration=iteration,
                    x=x.clone(),
                    cost=cost.clone(),
                    damping=mu.clone(),
                    step_norm=torch.where(running, step.norm(dim=1), zero),
                    accepted=accepted.clone(),
                    status=status.clone(),
                )
                if callback(record):
                    status = torch.where(status == LMStatus.RUNNING, int(LMStatus.STOPPED), status)

    return LMResult(x=x, cost=cost, status=status, n_iter=n_iter, nfev=nfev, njev=njev, damping=mu)


def _frozen(
    x: torch.Tensor,
    grad: torch.Tensor,
    fixed: torch.Tensor,
    lo: torch.Tensor | None,
    hi: torch.Tensor | None,
) -> torch.Tensor:
    """``(B, P)`` bool: variables held for this step (fixed, or on a bound with ``-g`` outward)."""
    frozen = fixed.clone()
    if lo is not None:
        frozen |= (x <= lo) & (grad > 0)
    if hi is not None:
        frozen |= (x >= hi) & (grad < 0)
    return frozen


def _geodesic_acceleration(
    residual_fn: ResidualFn,
    x: torch.Tensor,
    r: torch.Tensor,
    mask: torch.Tensor | None,
    jac: torch.Tensor,
    factor: torch.Tensor,
    vel: torch.Tensor,
    diag2: torch.Tensor,
    keep: torch.Tensor | None,
    solved: torch.Tensor,
    opts: LMOptions,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The step ``v + a/2`` with the geodesic acceleration ``a`` [Transtrum & Sethna 2012].

    ``r_vv ≈ (2/t) ((r(x + t v) - r(x)) / t - J v)`` (one residual evaluation, ``t = 0.1``) and
    ``a = -(JᵀJ + mu D²)⁻¹ Jᵀ r_vv`` with the Cholesky ``factor`` of the velocity's system.
    Where ``r(x + t v)`` or ``a`` is not finite, ``a = 0`` (the plain LM step).

    Returns:
        ``(h, too_curved, nfev)``: the step, a ``(B,)`` bool of steps with
        ``|D a| > accel_ratio |D v|`` (to reject) and the ``(B,)`` evaluations spent.
    """
    t = _ACCEL_FD_STEP
    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    x_fd = torch.where(solved[:, None], x + t * vel, x)
    r_fd, _ = evaluate_residual(residual_fn, x_fd, r.shape[1])
    jv = (jac @ vel[:, :, None])[:, :, 0]
    rvv = (2.0 / t) * ((r_fd - r) / t - jv)
    if mask is not None:
        rvv = torch.where(mask, rvv, zero)
    rhs = -(jac.transpose(1, 2) @ rvv[:, :, None])[:, :, 0]
    if keep is not None:
        rhs = rhs * keep
    acc = torch.cholesky_solve(rhs[:, :, None], factor)[:, :, 0]
    acc_ok = solved & torch.isfinite(acc).all(dim=1)
    acc = torch.where(acc_ok[:, None], acc, zero)
    dnorm = torch.sqrt(diag2)
    too_curved = acc_ok & ((dnorm * acc).norm(dim=1) > opts.accel_ratio * (dnorm * vel).norm(dim=1))
    return vel + 0.5 * acc, too_curved, solved.long()
