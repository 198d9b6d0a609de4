"""Pieces of one Levenberg–Marquardt step: the active set of the bounds and the geodesic
acceleration (see :func:`torchfit.solver.levenberg_marquardt` for the method)."""

from __future__ import annotations

import torch

from torchfit.solver.jacobians import ResidualFn, evaluate_residual
from torchfit.solver.normal import cholesky_solve_each, jacobian_t_times, jacobian_times
from torchfit.solver.options import LMOptions

__all__ = ["ACCEL_FD_STEP", "frozen_variables", "geodesic_acceleration"]

# Finite-difference step t along the velocity for the second directional derivative of the
# geodesic acceleration (Transtrum & Sethna 2012, section IV: t = 0.1).
ACCEL_FD_STEP = 0.1


def frozen_variables(
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


def geodesic_acceleration(
    residual_fn: ResidualFn,
    x: torch.Tensor,
    r: torch.Tensor,
    mask: torch.Tensor | None,
    valid: list[torch.Tensor | None],
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
    t = ACCEL_FD_STEP
    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    x_fd = torch.where(solved[:, None], x + t * vel, x)
    r_fd, _ = evaluate_residual(residual_fn, x_fd, r.shape[1])
    jv = jacobian_times(jac, vel, valid)
    rvv = (2.0 / t) * ((r_fd - r) / t - jv)
    if mask is not None:
        rvv = torch.where(mask, rvv, zero)
    rhs = -jacobian_t_times(jac, rvv, valid)
    if keep is not None:
        rhs = rhs * keep
    acc = cholesky_solve_each(rhs, factor)
    acc_ok = solved & torch.isfinite(acc).all(dim=1)
    acc = torch.where(acc_ok[:, None], acc, zero)
    dnorm = torch.sqrt(diag2)
    too_curved = acc_ok & ((dnorm * acc).norm(dim=1) > opts.accel_ratio * (dnorm * vel).norm(dim=1))
    return vel + 0.5 * acc, too_curved, solved.long()
