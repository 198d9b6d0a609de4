"""Batched Levenberg–Marquardt for ``B`` independent nonlinear least-squares problems.

The solver knows nothing of bodies, cameras or images: it takes a residual function
``(B, P) -> (B, M)`` (optionally with a validity mask), a start ``x0 (B, P)``, options and an
optional callback, and returns per-problem results, each the same as that problem solved alone.
Only running problems are stepped; with ``indexed=True`` the residual function is called as
``fn(x, index)`` for their rows alone. ``minpack_baseline`` runs the same residual function
through MINPACK's ``lmdif`` for comparison.

Example:
    >>> from torchfit.solver import levenberg_marquardt, LMOptions
    >>> result = levenberg_marquardt(residual_fn, x0, options=LMOptions(max_iter=50))
    >>> result.x, result.cost, result.status, result.message
"""

from torchfit.solver.heap import keep_heap
from torchfit.solver.jacobians import (
    jacobian_forward,
    jacobian_numeric,
    jacobian_reverse,
)
from torchfit.solver.lm import levenberg_marquardt
from torchfit.solver.minpack import minpack_baseline
from torchfit.solver.options import LMOptions, SolverError
from torchfit.solver.result import STATUS_MESSAGES, LMIterate, LMResult, LMStatus

__all__ = [
    "levenberg_marquardt",
    "minpack_baseline",
    "LMOptions",
    "LMResult",
    "LMIterate",
    "LMStatus",
    "STATUS_MESSAGES",
    "SolverError",
    "keep_heap",
    "jacobian_forward",
    "jacobian_reverse",
    "jacobian_numeric",
]
