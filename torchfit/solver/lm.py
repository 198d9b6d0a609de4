"""Batched Levenberg–Marquardt with per-problem damping, acceptance, convergence and failure.

Each of the ``B`` problems minimises ``F(x) = 0.5 * |r(x)|²`` on its own: every piece of state
(damping, scaling, counters, status) is a ``(B,)`` or ``(B, P)`` tensor, and a problem's
values are bit-for-bit those it has when solved alone, in any position of any batch:

- every iteration works on the *running* problems only (the active set is compacted: their
  rows are gathered, stepped and scattered back), so a problem that has converged or failed
  is no longer evaluated and costs the others nothing; with ``indexed=True`` the residual
  function is called on those rows alone;
- every sum over a problem's residual entries (the cost, ``JᵀJ``, ``Jᵀr``) is formed from
  that problem's own valid entries (:mod:`torchfit.solver.normal`): padding and the batch's
  size or order never change how they are grouped or which kernel rounds them.

One iteration, for every running problem (references in brackets):

1. After an accepted step (and at the start): the Jacobian ``J``, ``A = JᵀJ``, ``g = Jᵀr`` and
   Marquardt's scaling ``D² = diag(JᵀJ)`` [Marquardt 1963], kept non-decreasing as MINPACK's
   ``mode = 1`` does and clamped to ``[min_diag, max_diag]`` [Moré 1978; Ceres Solver's
   ``min_lm_diagonal`` / ``max_lm_diagonal``]; then the ``gtol`` test.
2. Solve ``(A + mu D²) h = -g`` by Cholesky (``torch.linalg.cholesky_ex``, per problem on
   the CPU: :func:`torchfit.solver.normal.cholesky_each`). The damped matrix
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

from torchfit.solver.iteration import lm_step, project, update_jacobian
from torchfit.solver.jacobians import (
    JacobianFn,
    ResidualFn,
    evaluate_residual,
    make_jacobian,
    rows_caller,
)
from torchfit.solver.normal import Block, valid_entries
from torchfit.solver.options import LMOptions, SolverError
from torchfit.solver.result import LMIterate, LMResult, LMStatus
from torchfit.solver.robust import check_loss_units, problem_cost

__all__ = ["levenberg_marquardt"]

Callback = Callable[[LMIterate], "bool | None"]


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
    indexed: bool = False,
    loss_units: torch.Tensor | None = None,
    jacobian_blocks: list[Block] | None = None,
    max_iter: torch.Tensor | None = None,
) -> LMResult:
    """Solve ``B`` independent nonlinear least-squares problems ``min_x 0.5 |r_b(x)|²``.

    Args:
        residual_fn: ``x (N, P) -> r (N, M)``, or ``-> (r, mask)`` with ``mask`` a ``(N, M)``
            bool tensor (``False`` entries are padding and count as zero in the cost and the
            Jacobian). Rows must be independent: row ``i`` of the output depends on row ``i``
            of the input only. ``N`` is ``B``, or ``K * B`` when a Jacobian is evaluated on
            ``K`` stacked copies of the batch (row ``i`` belongs to problem ``i % B``; see
            :attr:`LMOptions.fold_batch`). With ``indexed=True`` it is called as
            ``residual_fn(x, index)`` instead, ``index`` ``(N,)`` int64 giving the problem of
            each row, and only the running problems' rows are passed. For
            ``jacobian="autograd"`` it must be built from
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
            With ``indexed=True`` it is called as ``jacobian(x, index)``.
        callback: called after every iteration with an :class:`LMIterate` of detached values;
            returning ``True`` stops every running problem with status ``STOPPED``.
        lower, upper: optional bounds, ``(P,)`` or ``(B, P)``, ``±inf`` for none. Handled by
            projection (see the module docstring); ``lower == upper`` fixes a parameter.
        indexed: the residual function (and a callable ``jacobian``) takes the problem index
            of every row, and is evaluated for the running problems only. Without it the
            whole batch is evaluated each time (finished problems at their final ``x``, their
            rows discarded); results are the same, only the time differs.
        loss_units: optional ``(M,)`` or ``(B, M)`` size of one unit of
            :attr:`LMOptions.loss_scale` in each residual entry (``inf``: that entry stays least
            squares whatever :attr:`LMOptions.loss`); see :mod:`torchfit.solver.robust`.
        jacobian_blocks: optional sparsity of the Jacobian, the same for every problem:
            disjoint ranges of residual entries, each with the parameter columns it depends
            on (:data:`torchfit.solver.normal.Block`). The normal equations then sum
            ``J_kᵀ J_k`` over each block's own columns; a Jacobian that is not zero outside
            its blocks gets wrong normal equations.
        max_iter: optional ``(B,)`` integer limit on each problem's trial steps, in place of
            ``options.max_iter`` (problems that want more iterations than others share a
            batch: the others stop at their own limit, as they would alone).

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
    accel = opts.geodesic_acceleration
    fixed = torch.zeros(bsz, p, dtype=torch.bool, device=device)
    if lo is not None and hi is not None:
        fixed = lo == hi

    with torch.no_grad():
        x = project(x0.detach().clone(), lo, hi)
        everyone = torch.arange(bsz, device=device)
        r, mask = evaluate_residual(rows_caller(residual_fn, indexed, everyone, x), x)
        if r.dtype != dtype:
            raise SolverError(f"residual_fn: expected dtype {dtype} (that of x0), got {r.dtype}")
        m = r.shape[1]
        make_jacobian(jacobian, residual_fn, p, m, hi, opts.fold_batch)  # checks the argument
        _check_blocks(jacobian_blocks, m, p)
        units = check_loss_units(loss_units, r)
        cost = problem_cost(r, valid_entries(mask, bsz), opts.loss, opts.loss_scale, units)
        zeros = torch.zeros(bsz, dtype=dtype, device=device)
        counter = torch.zeros(bsz, dtype=torch.long, device=device)
        state = {
            "x": x,
            "r": r,
            "cost": cost,
            "status": torch.where(torch.isfinite(cost), counter, int(LMStatus.NONFINITE)),
            "mu": torch.full((bsz,), opts.initial_damping, dtype=dtype, device=device),
            "nu": torch.full((bsz,), 2.0, dtype=dtype, device=device),
            "diag2": torch.zeros(bsz, p, dtype=dtype, device=device),
            "a_mat": torch.zeros(bsz, p, p, dtype=dtype, device=device),
            "grad": torch.zeros(bsz, p, dtype=dtype, device=device),
            "gnorm": zeros,
            "need_jac": torch.ones(bsz, dtype=torch.bool, device=device),
            "n_iter": counter,
            "nfev": torch.ones(bsz, dtype=torch.long, device=device),
            "njev": counter,
            "bad": counter,
            "bad_kind": counter,
            "fixed": fixed,
            # free parameters per problem: what a Jacobian costs in evaluations for max_nfev
            "n_free": (~fixed).sum(dim=1),
        }
        if max_iter is not None:
            state["max_iter"] = _row_limits(max_iter, bsz, device)
        optional = {"mask": mask, "lo": lo, "hi": hi, "units": units}
        state.update({k: v for k, v in optional.items() if v is not None})
        if accel:  # the Jacobian of the last update, for J v in the geodesic acceleration
            state["jac"] = torch.zeros(bsz, m, p, dtype=dtype, device=device)
        iteration = 0

        while True:
            if not bool((state["status"] == LMStatus.RUNNING).any()):
                break
            iteration += 1
            x_all = state["x"]

            def jacobian_for(rows: torch.Tensor, idx: torch.Tensor, sub: dict, x_all=x_all):
                """The Jacobian routine of the active rows ``rows`` (positions in ``idx``)."""
                problems = idx[rows]
                fn = rows_caller(residual_fn, indexed, problems, x_all)
                jac = jacobian
                if callable(jacobian):
                    jac = rows_caller(jacobian, indexed, problems, x_all)
                hi_rows = sub["hi"][rows] if "hi" in sub else None
                return make_jacobian(jac, fn, p, m, hi_rows, opts.fold_batch)

            _on_running(
                state,
                lambda sub, idx: update_jacobian(
                    sub, lambda rows: jacobian_for(rows, idx, sub), opts, jacobian_blocks
                ),
            )
            # compacted again: a problem that stopped at the gradient test takes no step
            idx, out = _on_running(
                state,
                lambda sub, idx, x_all=x_all: lm_step(
                    sub, rows_caller(residual_fn, indexed, idx, x_all), opts
                ),
            )
            if idx is None or callback is None:
                continue
            step_norm, accepted = zeros.clone(), torch.zeros(bsz, dtype=torch.bool, device=device)
            step_norm[idx], accepted[idx] = out
            record = LMIterate(
                iteration=iteration,
                x=state["x"].clone(),
                cost=state["cost"].clone(),
                damping=state["mu"].clone(),
                step_norm=step_norm,
                accepted=accepted,
                status=state["status"].clone(),
            )
            if callback(record):
                status = state["status"]
                state["status"] = torch.where(
                    status == LMStatus.RUNNING, int(LMStatus.STOPPED), status
                )

    s = state
    return LMResult(
        x=s["x"],
        cost=s["cost"],
        status=s["status"],
        n_iter=s["n_iter"],
        nfev=s["nfev"],
        njev=s["njev"],
        damping=s["mu"],
        residual=s["r"],
    )


def _row_limits(limits: torch.Tensor, bsz: int, device) -> torch.Tensor:
    """The per-problem ``max_iter`` as a (B,) long tensor; raises :class:`SolverError`."""
    if not isinstance(limits, torch.Tensor) or tuple(limits.shape) != (bsz,):
        got = tuple(limits.shape) if isinstance(limits, torch.Tensor) else type(limits).__name__
        raise SolverError(f"max_iter: expected a ({bsz},) tensor, got {got}")
    if limits.is_floating_point() or bool((limits < 1).any()):
        raise SolverError("max_iter: expected integers >= 1")
    return limits.to(device=device, dtype=torch.long)


def _check_blocks(blocks: list[Block] | None, m: int, p: int) -> None:
    """Raise :class:`SolverError` for a block outside the ``(M, P)`` Jacobian."""
    for rows, cols in blocks or []:
        if not isinstance(rows, slice) or rows.step not in (None, 1):
            raise SolverError(f"jacobian_blocks: expected row ranges as slices, got {rows!r}")
        bad = cols.numel() and (int(cols.min()) < 0 or int(cols.max()) >= p)
        if rows.start is None or rows.stop is None or not 0 <= rows.start < rows.stop <= m or bad:
            raise SolverError(
                f"jacobian_blocks: rows {rows} / columns outside the ({m}, {p}) Jacobian"
            )


def _on_running(state: dict, work: Callable[[dict, torch.Tensor], object]):
    """Run ``work(sub, idx)`` on the running problems' rows ``sub`` (``idx`` their indices)
    and scatter the rows back: the active set is compacted. Returns ``(idx, result)``, or
    ``(None, None)`` when no problem is running."""
    idx = (state["status"] == LMStatus.RUNNING).nonzero()[:, 0]
    if idx.numel() == 0:
        return None, None
    whole = idx.numel() == state["x"].shape[0]
    sub = state if whole else {k: v[idx] for k, v in state.items()}
    out = work(sub, idx)
    if not whole:
        for key, value in sub.items():
            state[key] = state[key].index_copy(0, idx, value)
    return idx, out
