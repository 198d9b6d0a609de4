"""Options of the Levenberg–Marquardt solver and its error type.

Tolerances follow MINPACK's ``lmder``/``lmdif`` (Moré, Garbow, Hillstrom, "User Guide for
MINPACK-1", ANL-80-74, 1980): ``ftol`` bounds the relative reduction of the sum of squares,
``xtol`` the relative size of the scaled step, ``gtol`` the cosine between the residual and the
columns of the Jacobian.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from torchfit.errors import TorchfitError

__all__ = ["LMOptions", "SolverError", "LOSSES"]

#: The robust losses of :mod:`torchfit.solver.robust`.
LOSSES: tuple[str, ...] = ("linear", "huber", "cauchy")


class SolverError(TorchfitError):
    """Bad input to the solver (options, shapes, a residual or Jacobian of the wrong shape)."""


@dataclass(frozen=True)
class LMOptions:
    """Options of :func:`torchfit.solver.levenberg_marquardt` (the same for every problem).

    Attributes:
        max_iter: trial steps per problem (each costs one residual evaluation, two with
            ``geodesic_acceleration``; a new Jacobian is computed only after an accepted step).
            Status ``MAX_ITER`` when reached.
        ftol: stop when both the actual and the predicted relative reduction of the cost are
            at most ``ftol`` (MINPACK info 1).
        xtol: stop when the scaled step ``|D h|`` is at most ``xtol * |D x|`` (MINPACK info 2).
        gtol: stop when the largest cosine between the residual and a Jacobian column is at
            most ``gtol`` (MINPACK info 4).
        initial_damping: ``mu`` at the start; the damped system is ``(JᵀJ + mu D²) h = -Jᵀr``.
        min_diag, max_diag: clamp of the scaling ``D² = diag(JᵀJ)``.
        accept_ratio: a step is accepted when the gain ratio exceeds this (MINPACK: 1e-4).
        max_bad_steps: consecutive trial steps with a failed Cholesky factorisation or a
            non-finite residual after which a problem fails (status ``NONFINITE`` or
            ``LINALG``); each bad step multiplies its damping as a rejection does.
        step_bound: MINPACK's ``factor``: a step longer than ``step_bound * |D x|`` (scaled
            norms; ``step_bound`` where ``x = 0``) is shortened to that length. ``None``
            disables it.
        fold_batch: evaluate forward-mode and finite-difference Jacobians with one call of the
            residual function on ``K`` stacked copies of the batch, ``(K*B, P)`` (row ``i``
            belongs to problem ``i % B``). ``False`` makes ``K`` calls on ``(B, P)`` instead.
            Forward mode makes ``P`` calls on ``(B, P)`` anyway when one copy already holds
            ``torchfit.solver.jacobians.FORWARD_UNFOLD_MIN_RESIDUALS`` residuals (``B * M``).
        geodesic_acceleration: add Transtrum & Sethna's second-order correction to each step
            (one more residual evaluation per trial step; see
            :func:`~torchfit.solver.levenberg_marquardt`). Helps on narrow curved valleys and
            against parameters running off to infinity.
        accel_ratio: with ``geodesic_acceleration``, reject a trial step whose acceleration is
            large against its velocity, ``|D a| > accel_ratio * |D v|`` (Transtrum & Sethna
            suggest 0.75).
        max_nfev: a budget of residual evaluations per problem, or ``None``. Counted as
            MINPACK's ``lmdif`` counts its ``nfev``: every residual evaluation (trial points,
            acceleration probes) plus, per Jacobian, one per free parameter (a parameter whose
            bounds are not equal), which is what a forward-difference Jacobian costs. Status
            ``MAX_ITER`` (MINPACK's info 5) when reached; checked after each iteration.
        loss: ``"linear"`` (least squares), ``"huber"`` or ``"cauchy"``: the robust loss of
            each residual entry, applied inside the normal equations by Triggs' correction
            (:mod:`torchfit.solver.robust`); the cost is then ``½ Σ ρ(r²)``.
        loss_scale: the loss's scale ``a``: where ``|r|`` exceeds it, Huber grows linearly and
            Cauchy logarithmically. In the residual's own units, or in those the caller gives
            per entry (``loss_units`` of :func:`~torchfit.solver.levenberg_marquardt`).
    """

    max_iter: int = 100
    ftol: float = 1e-8
    xtol: float = 1e-8
    gtol: float = 1e-10
    initial_damping: float = 1e-3
    min_diag: float = 1e-12
    max_diag: float = 1e32
    accept_ratio: float = 1e-4
    max_bad_steps: int = 10
    step_bound: float | None = 100.0
    fold_batch: bool = True
    geodesic_acceleration: bool = False
    accel_ratio: float = 0.75
    max_nfev: int | None = None
    loss: Literal["linear", "huber", "cauchy"] = "linear"
    loss_scale: float = 1.0

    def __post_init__(self) -> None:
        if isinstance(self.max_iter, bool) or not isinstance(self.max_iter, int):
            raise SolverError(f"LMOptions.max_iter: expected an int, got {self.max_iter!r}")
        if self.max_iter < 1:
            raise SolverError(f"LMOptions.max_iter: expected >= 1, got {self.max_iter}")
        for name in ("ftol", "xtol", "gtol"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise SolverError(f"LMOptions.{name}: expected a finite number >= 0, got {value!r}")
        for name in ("initial_damping", "min_diag", "max_diag"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise SolverError(f"LMOptions.{name}: expected a finite number > 0, got {value!r}")
        if self.step_bound is not None and (
            not isinstance(self.step_bound, (int, float))
            or not math.isfinite(self.step_bound)
            or self.step_bound <= 0
        ):
            raise SolverError(
                f"LMOptions.step_bound: expected None or a finite number > 0, got "
                f"{self.step_bound!r}"
            )
        if self.min_diag > self.max_diag:
            raise SolverError(
                f"LMOptions.min_diag: expected <= max_diag ({self.max_diag}), got {self.min_diag}"
            )
        if not 0 <= self.accept_ratio < 1:
            raise SolverError(
                f"LMOptions.accept_ratio: expected a number in [0, 1), got {self.accept_ratio!r}"
            )
        if isinstance(self.max_bad_steps, bool) or not isinstance(self.max_bad_steps, int):
            raise SolverError(
                f"LMOptions.max_bad_steps: expected an int, got {self.max_bad_steps!r}"
            )
        if self.max_bad_steps < 1:
            raise SolverError(f"LMOptions.max_bad_steps: expected >= 1, got {self.max_bad_steps}")
        if not isinstance(self.geodesic_acceleration, bool):
            raise SolverError(
                f"LMOptions.geodesic_acceleration: expected a bool, got "
                f"{self.geodesic_acceleration!r}"
            )
        if (
            isinstance(self.accel_ratio, bool)
            or not isinstance(self.accel_ratio, (int, float))
            or not math.isfinite(self.accel_ratio)
            or self.accel_ratio <= 0
        ):
            raise SolverError(
                f"LMOptions.accel_ratio: expected a finite number > 0, got {self.accel_ratio!r}"
            )
        if self.max_nfev is not None and (
            isinstance(self.max_nfev, bool)
            or not isinstance(self.max_nfev, int)
            or self.max_nfev < 1
        ):
            raise SolverError(
                f"LMOptions.max_nfev: expected None or an int >= 1, got {self.max_nfev!r}"
            )
        if self.loss not in LOSSES:
            raise SolverError(f"LMOptions.loss: expected one of {list(LOSSES)}, got {self.loss!r}")
        if (
            isinstance(self.loss_scale, bool)
            or not isinstance(self.loss_scale, (int, float))
            or not math.isfinite(self.loss_scale)
            or self.loss_scale <= 0
        ):
            raise SolverError(
                f"LMOptions.loss_scale: expected a finite number > 0, got {self.loss_scale!r}"
            )
