"""Robust loss functions inside the normal equations (Triggs' correction, as Ceres Solver does).

Each scalar residual ``r`` with ``s = r²`` contributes ``ρ(s) / 2`` to the cost instead of
``s / 2``; every entry is its own residual block. For a scale ``a`` (``b = a²``), in the
residual's own units:

- ``linear``: ``ρ(s) = s`` (least squares);
- ``huber``: ``ρ(s) = s`` for ``s <= b``, ``2 sqrt(b s) - b`` beyond (linear growth of |r|);
- ``cauchy``: ``ρ(s) = b log(1 + s / b)`` (logarithmic growth).

The Levenberg–Marquardt step keeps its Gauss–Newton form through the correction of Triggs,
McLauchlan, Hartley & Fitzgibbon (Bundle Adjustment — A Modern Synthesis, 2000, section 4.3)
as Ceres' ``Corrector`` applies it (``internal/ceres/corrector.cc``): with ``ρ'`` and ``ρ''`` at
``s``,

- where ``ρ'' <= 0`` or ``s = 0``: ``r̃ = sqrt(ρ') r`` and ``J̃ = sqrt(ρ') J``;
- where ``ρ'' > 0``: ``α = 1 - sqrt(1 + 2 s ρ''/ρ')``, ``r̃ = sqrt(ρ') / (1 - α) r`` and
  ``J̃ = sqrt(ρ') (1 - α) J``.

Then ``J̃ᵀ r̃ = ρ' Jᵀ r`` is the gradient of ``½ Σ ρ(r²)`` and ``J̃ᵀ J̃`` its Gauss–Newton
Hessian (with the second-order term of ``ρ`` where ``ρ'' > 0``). Huber and Cauchy have
``ρ'' <= 0``, so for them the correction is the plain reweighting.

Per-entry units: ``loss_units`` (``(M,)`` or ``(B, M)``) gives the size of one unit of
``loss_scale`` in each entry, so that an entry ``e = d / c`` (a distance ``d`` normalised by
``c``) is judged on ``d``: its scale is ``a = loss_scale * units`` with ``units = 1 / c``. Both
losses are homogeneous, ``ρ_{a/c}(s/c²) = ρ_a(c² s) / c²``, so this is the loss of ``d``
weighted by ``1/c²``. An entry with infinite units stays least squares.
"""

from __future__ import annotations

import torch

from torchfit.solver.normal import half_squared_norm, half_sum
from torchfit.solver.options import LOSSES, SolverError

__all__ = [
    "LOSSES",
    "loss_rho",
    "robust_cost",
    "problem_cost",
    "robust_correct",
    "check_loss_units",
]


def check_loss_units(units: torch.Tensor | None, r: torch.Tensor) -> torch.Tensor | None:
    """``units`` as a ``(B, M)`` tensor like ``r`` (None stays None).

    Raises:
        SolverError: a shape other than ``(M,)`` or ``(B, M)``, or entries that are not > 0.
    """
    if units is None:
        return None
    b, m = r.shape
    units = torch.as_tensor(units, dtype=r.dtype, device=r.device)
    if tuple(units.shape) not in ((m,), (b, m)):
        raise SolverError(
            f"loss_units: expected shape ({m},) or ({b}, {m}), got {tuple(units.shape)}"
        )
    if not bool((units > 0).all()):
        raise SolverError("loss_units: expected entries > 0 (inf for least squares)")
    return units.expand(b, m)


def loss_rho(loss: str, s: torch.Tensor, scale: torch.Tensor | float) -> tuple[torch.Tensor, ...]:
    """``(ρ(s), ρ'(s), ρ''(s))`` of a loss at ``s = r² >= 0`` for scale ``a`` (``inf``: linear).

    Args:
        loss: one of :data:`LOSSES`.
        s: squared residuals, any shape.
        scale: ``a``, broadcastable to ``s`` (> 0).
    """
    one, zero = torch.ones_like(s), torch.zeros_like(s)
    if loss == "linear":
        return s, one, zero
    b = torch.as_tensor(scale, dtype=s.dtype, device=s.device) ** 2
    b = b.expand_as(s)
    finite = torch.isfinite(b)
    b_safe = torch.where(finite, b, one)
    if loss == "huber":
        outer = finite & (s > b_safe)
        s_safe = torch.where(outer, s, one)
        root = torch.sqrt(b_safe * s_safe)
        rho1_out = torch.sqrt(b_safe / s_safe)
        rho0 = torch.where(outer, 2 * root - b_safe, s)
        rho1 = torch.where(outer, rho1_out, one)
        rho2 = torch.where(outer, -rho1_out / (2 * s_safe), zero)
        return rho0, rho1, rho2
    if loss == "cauchy":
        q = torch.where(finite, s / b_safe, zero)
        rho1_c = 1 / (1 + q)
        rho0 = torch.where(finite, b_safe * torch.log1p(q), s)
        rho1 = torch.where(finite, rho1_c, one)
        rho2 = torch.where(finite, -rho1_c * rho1_c / b_safe, zero)
        return rho0, rho1, rho2
    raise SolverError(f"loss: expected one of {list(LOSSES)}, got {loss!r}")


def _scale(scale: float, units: torch.Tensor | None) -> torch.Tensor | float:
    return scale if units is None else scale * units


def robust_cost(
    r: torch.Tensor, loss: str, scale: float, units: torch.Tensor | None = None
) -> torch.Tensor:
    """``(B,)`` cost ``½ Σ_i ρ(r_i²)`` of residuals ``r`` (B, M).

    Args:
        r: residuals (zero on padding, where ``ρ(0) = 0``).
        loss: one of :data:`LOSSES`.
        scale: ``loss_scale`` in the units of ``units`` (the residual's own where None).
        units: optional ``(B, M)`` per-entry size of one unit (see the module docstring).
    """
    if loss == "linear":
        return 0.5 * (r * r).sum(dim=1)
    rho0, _, _ = loss_rho(loss, r * r, _scale(scale, units))
    return 0.5 * rho0.sum(dim=1)


def problem_cost(
    r: torch.Tensor,
    valid: list[torch.Tensor | None],
    loss: str,
    scale: float,
    units: torch.Tensor | None = None,
) -> torch.Tensor:
    """:func:`robust_cost` over each problem's valid entries, summed one problem at a time
    (:mod:`torchfit.solver.normal`), so that a problem's cost does not depend on its batch."""
    if loss == "linear":
        return half_squared_norm(r, valid)
    rho0, _, _ = loss_rho(loss, r * r, _scale(scale, units))
    return half_sum(rho0, valid)


def robust_correct(
    jac: torch.Tensor,
    r: torch.Tensor,
    loss: str,
    scale: float,
    units: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Triggs' correction ``(J̃, r̃)`` of a Jacobian ``jac`` (B, M, P) and residuals ``r`` (B, M).

    ``J̃ᵀ J̃`` and ``J̃ᵀ r̃`` are the Gauss–Newton normal equations of ``½ Σ ρ(r_i²)``. For
    ``loss == "linear"`` the inputs are returned as they are.
    """
    if loss == "linear":
        return jac, r
    s = r * r
    _, rho1, rho2 = loss_rho(loss, s, _scale(scale, units))
    sqrt_rho1 = torch.sqrt(rho1)
    second = (rho2 > 0) & (s > 0)
    # Ceres' Corrector: alpha solves 0.5 alpha² - alpha - (s rho'' / rho') = 0.
    d = 1 + 2 * s * rho2 / rho1
    alpha = torch.where(second, 1 - torch.sqrt(torch.where(second, d, torch.ones_like(d))), 0.0)
    r_scale = sqrt_rho1 / (1 - alpha)
    j_scale = sqrt_rho1 * (1 - alpha)
    return jac * j_scale[:, :, None], r * r_scale
