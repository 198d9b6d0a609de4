"""Result, status codes and per-iteration record of the Levenberg–Marquardt solver.

Status codes 1–8 carry MINPACK's meaning of ``info`` (``lmder``/``lmdif``, Moré et al.,
ANL-80-74, 1980); 0 marks a problem still running and 9–11 are failures of one problem that
MINPACK does not have (non-finite values, failed factorisation, a stop asked by the callback).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import torch

__all__ = ["LMStatus", "LMResult", "LMIterate", "STATUS_MESSAGES"]


class LMStatus(IntEnum):
    """Per-problem status of :func:`~torchfit.solver.levenberg_marquardt`."""

    RUNNING = 0
    FTOL = 1
    XTOL = 2
    FTOL_XTOL = 3
    GTOL = 4
    MAX_ITER = 5
    FTOL_TOO_SMALL = 6
    XTOL_TOO_SMALL = 7
    GTOL_TOO_SMALL = 8
    NONFINITE = 9
    LINALG = 10
    STOPPED = 11

    @property
    def success(self) -> bool:
        """True for the converged codes 1–4 (as MINPACK and ``scipy.optimize.leastsq``)."""
        return self in (LMStatus.FTOL, LMStatus.XTOL, LMStatus.FTOL_XTOL, LMStatus.GTOL)

    @property
    def message(self) -> str:
        """The status in words."""
        return STATUS_MESSAGES[self]


STATUS_MESSAGES: dict[LMStatus, str] = {
    LMStatus.RUNNING: "still running",
    LMStatus.FTOL: "both actual and predicted relative reductions in the sum of squares are "
    "at most ftol",
    LMStatus.XTOL: "relative error between two consecutive iterates is at most xtol",
    LMStatus.FTOL_XTOL: "both actual and predicted relative reductions in the sum of squares "
    "are at most ftol and the relative error between two consecutive iterates is at most xtol",
    LMStatus.GTOL: "the cosine of the angle between the residual and any column of the "
    "Jacobian is at most gtol in absolute value",
    LMStatus.MAX_ITER: "number of iterations reached max_iter (or residual evaluations max_nfev)",
    LMStatus.FTOL_TOO_SMALL: "ftol is too small: no further reduction in the sum of squares "
    "is possible",
    LMStatus.XTOL_TOO_SMALL: "xtol is too small: no further improvement in the approximate "
    "solution x is possible",
    LMStatus.GTOL_TOO_SMALL: "gtol is too small: the residual is orthogonal to the columns of "
    "the Jacobian to machine precision",
    LMStatus.NONFINITE: "the residual or its Jacobian is not finite (at the start, or on "
    "max_bad_steps consecutive trial steps)",
    LMStatus.LINALG: "the damped normal equations could not be factorised on max_bad_steps "
    "consecutive trial steps",
    LMStatus.STOPPED: "stopped by the callback",
}


@dataclass
class LMResult:
    """Per-problem result of a batched solve (all tensors detached).

    Attributes:
        x: ``(B, P)`` final parameters.
        cost: ``(B,)`` ``0.5 * |r(x)|²`` (masked residual entries count as zero).
        status: ``(B,)`` int64, values of :class:`LMStatus`.
        n_iter: ``(B,)`` int64, trial steps taken.
        nfev: ``(B,)`` int64, residual evaluations (Jacobian evaluations not included;
            acceleration probes included).
        njev: ``(B,)`` int64, Jacobian evaluations.
        damping: ``(B,)`` final damping ``mu``.
        residual: ``(B, M)`` the residual at ``x`` (the last one evaluated there), or None.
    """

    x: torch.Tensor
    cost: torch.Tensor
    status: torch.Tensor
    n_iter: torch.Tensor
    nfev: torch.Tensor
    njev: torch.Tensor
    damping: torch.Tensor
    residual: torch.Tensor | None = None

    @property
    def statuses(self) -> list[LMStatus]:
        """The status of each problem as :class:`LMStatus`."""
        return [LMStatus(int(s)) for s in self.status.tolist()]

    @property
    def message(self) -> list[str]:
        """One message per problem, MINPACK-style."""
        return [s.message for s in self.statuses]

    @property
    def success(self) -> torch.Tensor:
        """``(B,)`` bool: converged by ftol, xtol or gtol (codes 1–4)."""
        return (self.status >= LMStatus.FTOL) & (self.status <= LMStatus.GTOL)


@dataclass
class LMIterate:
    """What the callback receives after every iteration (detached per-problem values).

    Attributes:
        iteration: 1-based iteration number of the batch.
        x: ``(B, P)`` current (accepted) parameters.
        cost: ``(B,)`` current cost ``0.5 * |r|²``.
        damping: ``(B,)`` damping ``mu`` for the next step.
        step_norm: ``(B,)`` Euclidean norm of this iteration's trial step (0 where none).
        accepted: ``(B,)`` bool, the trial step was accepted.
        status: ``(B,)`` int64 :class:`LMStatus` values (0 while running).
    """

    iteration: int
    x: torch.Tensor
    cost: torch.Tensor
    damping: torch.Tensor
    step_norm: torch.Tensor
    accepted: torch.Tensor
    status: torch.Tensor
