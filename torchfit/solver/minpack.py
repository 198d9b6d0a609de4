"""MINPACK baseline: the same residual function through ``scipy.optimize.leastsq`` (lmdif).

``scipy.optimize.leastsq`` without ``Dfun`` calls MINPACK's ``lmdif`` (forward-difference
Jacobian, Moré's trust-region LM with ``mode = 1`` scaling), one problem at a time. The result has
the type of :func:`~torchfit.solver.levenberg_marquardt`'s, with MINPACK's ``info`` as status.
"""

from __future__ import annotations

import numpy as np
import torch

from torchfit.solver.jacobians import ResidualFn, evaluate_residual
from torchfit.solver.options import LMOptions, SolverError
from torchfit.solver.result import LMResult, LMStatus

__all__ = ["minpack_baseline"]


def minpack_baseline(
    residual_fn: ResidualFn,
    x0: torch.Tensor,
    options: LMOptions | None = None,
    max_nfev: int | None = None,
    epsfcn: float | None = None,
) -> LMResult:
    """Solve each problem of the batch alone with MINPACK's ``lmdif``.

    Problem ``b`` is evaluated by calling ``residual_fn`` on a ``(B, P)`` batch whose row ``b``
    is MINPACK's point and whose other rows hold their ``x0`` (the residual function's contract
    makes rows independent). That costs a full-batch evaluation per call: for a fair timing,
    call this once per problem with ``B = 1`` residual functions. Masked residual entries are
    passed to MINPACK as zeros.

    Args:
        residual_fn: as for :func:`~torchfit.solver.levenberg_marquardt` (``(B, P) -> (B, M)``
            or ``(r, mask)``); it is only ever called on ``B`` rows.
        x0: ``(B, P)`` start; results come back in its dtype and device (MINPACK runs in
            float64).
        options: ``ftol``, ``xtol``, ``gtol`` go to MINPACK as they are; ``maxfev`` is
            ``max_nfev`` (the argument), else ``options.max_nfev`` (the same budget the LM
            solver then gets, counted the same way), else ``max_iter * (P + 1)`` (each MINPACK
            iteration spends ``P`` evaluations on the Jacobian and one on the trial point).
        max_nfev: MINPACK's ``maxfev`` (residual evaluations, Jacobian columns included).
        epsfcn: MINPACK's ``epsfcn``: the forward-difference step is
            ``sqrt(max(epsfcn, eps)) * |x_j|`` (default: machine precision). Residuals that
            are piecewise constant at small scales (rendered pixels) need a larger value.

    Returns:
        :class:`~torchfit.solver.LMResult`: ``status`` is MINPACK's ``info`` (1–8; 0 for
        improper input), ``nfev`` MINPACK's count (finite-difference columns included),
        ``n_iter`` equal to ``nfev``, ``njev`` 0 (lmdif does not report it) and ``damping``
        NaN (lmdif keeps a trust region, not a damping).

    Raises:
        SolverError: for a bad ``x0`` or options, or a residual of the wrong shape.
    """
    from scipy.optimize import leastsq  # imported here: scipy loads only when the baseline runs

    opts = options if options is not None else LMOptions()
    if not isinstance(x0, torch.Tensor) or x0.dim() != 2 or not x0.is_floating_point():
        raise SolverError("x0: expected a floating-point tensor of shape (B, P)")
    bsz, p = x0.shape
    if max_nfev is None:
        max_nfev = opts.max_nfev if opts.max_nfev is not None else opts.max_iter * (p + 1)
    maxfev = int(max_nfev)
    x0_64 = x0.detach().to(torch.float64)
    with torch.no_grad():
        r0, _ = evaluate_residual(residual_fn, x0.detach())
    m = r0.shape[1]
    xs, costs, statuses, nfevs = [], [], [], []
    for b in range(bsz):

        def fun(v: np.ndarray, b: int = b) -> np.ndarray:
            batch = x0_64.clone()
            batch[b] = torch.from_numpy(np.asarray(v, dtype=np.float64))
            with torch.no_grad():
                r, _ = evaluate_residual(residual_fn, batch.to(x0.dtype), m)
            return r[b].to(torch.float64).cpu().numpy()

        sol, _, info, _, ier = leastsq(
            fun,
            x0_64[b].numpy(),
            full_output=True,
            ftol=opts.ftol,
            xtol=opts.xtol,
            gtol=opts.gtol,
            maxfev=maxfev,
            epsfcn=epsfcn,
        )
        sol = np.atleast_1d(sol)
        fvec = info["fvec"]
        xs.append(torch.from_numpy(sol.astype(np.float64)))
        costs.append(0.5 * float(np.dot(fvec, fvec)))
        statuses.append(int(ier) if 1 <= int(ier) <= 8 else int(LMStatus.RUNNING))
        nfevs.append(int(info["nfev"]))
    as_long = {"dtype": torch.long, "device": x0.device}
    nfev = torch.tensor(nfevs, **as_long)
    return LMResult(
        x=torch.stack(xs).to(dtype=x0.dtype, device=x0.device),
        cost=torch.tensor(costs, dtype=x0.dtype, device=x0.device),
        status=torch.tensor(statuses, **as_long),
        n_iter=nfev.clone(),
        nfev=nfev,
        njev=torch.zeros(bsz, **as_long),
        damping=torch.full((bsz,), float("nan"), dtype=x0.dtype, device=x0.device),
    )
