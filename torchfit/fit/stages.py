"""One stage of the fit: Levenberg–Marquardt over a subset of the parameters.

A stage frees some scale groups and, for every posture, its joints and/or its root offsets;
the other parameters stay where the previous stage left them. The discrete model-contour
choice is held fixed while the solver tries steps, so every trial is judged on the same smooth
objective, and it is refreshed at each accepted point (where the Jacobian is computed).

The solver itself always works in float64: in a float32 fit (the model's dtype) the posing,
projection, contour choice, residuals and Jacobian run in float32 and are widened for the
solver, which keeps the parameters, the normal equations ``JᵀJ``, ``Jᵀr``, the Cholesky
solve, the cost and its convergence tests in float64 (float32 cannot resolve a relative change
of the parameters below about 1e-7, nor a relative reduction of the cost of the order of the
tolerances). In a float64 fit nothing is converted. The forward-difference Jacobian
(``"numeric"``, for checks) steps by the square root of the solver's machine epsilon, so with
it the solver stays in the model's dtype.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import torch

from torchfit.fit.model_contour import ContourSelection
from torchfit.fit.problem import SilhouetteFit
from torchfit.solver import LMOptions, LMResult, levenberg_marquardt
from torchfit.solver.jacobians import make_jacobian

__all__ = [
    "StageOptions",
    "JACOBIANS",
    "SOLVER_DTYPE",
    "solve_stage",
    "pose_contour_rms",
    "pose_outliers",
]

#: The dtype of the solver's state in a stage, whatever the model's (but with the
#: ``"numeric"`` Jacobian; see the module docstring).
SOLVER_DTYPE = torch.float64

#: The Jacobians a stage can use: ``"autograd"`` the problem's own (forward-mode pixel
#: tangents of the contour vertices times reverse-mode local derivatives, per posture);
#: ``"forward"``, ``"reverse"`` and ``"numeric"`` the solver's generic forward-mode,
#: reverse-mode and forward-difference Jacobians of the whole residual (slower; for checks).
JACOBIANS: tuple[str, ...] = ("autograd", "forward", "reverse", "numeric")


@dataclass(frozen=True)
class StageOptions:
    """One stage of the fit schedule.

    Attributes:
        name: the stage's name (in logs, TensorBoard tags and params.json).
        scales: the free scale groups: group names, aliases (``legs``, ``upper_body``),
            ``"group:axes"`` or ``"all"``.
        joints: optimise every posture's free joint angles.
        root: optimise every posture's floor translation and rotation.
        max_iter: the stage's own iteration limit (None: the solver's).
        loss: the stage's own robust loss (:attr:`torchfit.solver.LMOptions.loss`; None: the
            solver's). A robust loss holds back the pull of contour pixels far from the model,
            which is what a first stage from the template needs to bring a limb that starts
            far from its place, so the shipped schedules keep their first stage ``linear``.
    """

    name: str = "all"
    scales: tuple[str, ...] = field(default_factory=lambda: ("all",))
    joints: bool = True
    root: bool = True
    max_iter: int | None = None
    loss: Literal["linear", "huber", "cauchy"] | None = None


def solve_stage(
    fit: SilhouetteFit,
    full: torch.Tensor,
    stage: StageOptions,
    options: LMOptions,
    jacobian: Literal["autograd", "forward", "reverse", "numeric"] = "autograd",
    callback: Callable | None = None,
) -> tuple[torch.Tensor, LMResult]:
    """Run LM over one stage's free parameters.

    Args:
        fit: the problem.
        full: (B, P) parameters at the start of the stage.
        stage: which parameters the stage frees.
        options: solver options (``max_iter`` as the stage wants it).
        jacobian: one of :data:`JACOBIANS`.
        callback: optional solver callback (:class:`torchfit.solver.LMIterate` per iteration).

    Returns:
        (B, P) parameters after the stage (in ``full``'s dtype), and the solver's result
        over the free ones (in :data:`SOLVER_DTYPE`, see the module docstring).

    Raises:
        ValueError: an unknown ``jacobian``.
    """
    if jacobian not in JACOBIANS:
        raise ValueError(f"jacobian: expected one of {list(JACOBIANS)}, got {jacobian!r}")
    free = fit.stage_indices(list(stage.scales), stage.joints, stage.root)
    work = fit.kw["dtype"]
    solver_dtype = work if jacobian == "numeric" else SOLVER_DTYPE
    base = full.detach().to(solver_dtype, copy=True)
    mask = fit.residual_mask()
    chosen = _Selections(fit)
    onehot = torch.zeros(free.numel(), base.shape[1], dtype=solver_dtype, device=base.device)
    onehot[torch.arange(free.numel()), free] = 1.0

    def expand(x: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        # exact: each column of x @ onehot holds one x entry (times 1) and zeros; then in the
        # model's dtype (a float32 fit rounds the solver's float64 parameters here)
        return (base[rows] * (1 - onehot.sum(0)) + x @ onehot).to(work)

    def residual_fn(x: torch.Tensor, rows: torch.Tensor):
        full_x = expand(x, rows)
        r = fit.residual(full_x, chosen.take(rows, full_x), rows)
        return r.to(solver_dtype), mask[rows]

    def own_jacobian(x: torch.Tensor, rows: torch.Tensor):
        full_x = expand(x, rows)
        sel = chosen.refresh(rows, full_x)
        jac, r = fit.jacobian_and_residual(full_x, free, sel, rows)
        return jac.to(solver_dtype), r.to(solver_dtype)

    def generic_jacobian(x: torch.Tensor, rows: torch.Tensor):
        chosen.refresh(rows, expand(x, rows))
        r, _ = residual_fn(x, rows)
        n = rows.numel()
        generic = make_jacobian(
            jacobian if jacobian != "autograd" else "forward",
            lambda xx: residual_fn(xx, rows.repeat(xx.shape[0] // n)),
            free.numel(),
            mask.shape[1],
            None,
            options.fold_batch,
        )
        return generic(x, r, mask[rows]), r

    x0 = base[:, free].clone()
    result = levenberg_marquardt(
        residual_fn,
        x0,
        options=options,
        jacobian=own_jacobian if jacobian == "autograd" else generic_jacobian,
        callback=callback,
        indexed=True,
        loss_units=fit.loss_units().to(solver_dtype),
        jacobian_blocks=fit.jacobian_blocks(free),
    )
    out = full.detach().clone()
    out[:, free] = result.x.to(out.dtype)
    return out, result


class _Selections:
    """The current contour choice of every subject of a stage.

    The solver evaluates only its running subjects (rows ``rows`` of the batch); a subject's
    choice is made at its first evaluation and remade where its Jacobian is (after each
    accepted step), whatever the others are doing.
    """

    def __init__(self, fit: SilhouetteFit) -> None:
        self.fit = fit
        self.chosen: dict[int, ContourSelection] | None = None
        self.have = torch.zeros(fit.batch, dtype=torch.bool)

    def refresh(self, rows: torch.Tensor, full: torch.Tensor) -> dict[int, ContourSelection]:
        """Remake the choice of the subjects ``rows`` (N,) at their parameters ``full`` (N, P);
        returns it."""
        new = self.fit.select(full, rows)
        if self.chosen is None:
            everyone = torch.arange(self.fit.batch)
            # placeholders for the subjects not chosen yet (never read before they are)
            self.chosen = {j: sel.take(torch.zeros_like(everyone)) for j, sel in new.items()}
        self.chosen = {j: self.chosen[j].put(rows.cpu(), new[j]) for j in new}
        self.have[rows.cpu()] = True
        return new

    def take(self, rows: torch.Tensor, full: torch.Tensor) -> dict[int, ContourSelection]:
        """The choice of the rows' subjects (N,) (made at ``full`` (N, P) where there is none:
        a folded evaluation repeats rows, and only the first copy is used then)."""
        at = rows.cpu()
        missing = ~self.have[at]
        if bool(missing.any()):
            subjects = torch.unique(at[missing])
            first = torch.stack([(at == i).nonzero()[0, 0] for i in subjects])
            self.refresh(subjects.to(rows.device), full[first.to(full.device)])
        return {j: sel.take(at) for j, sel in self.chosen.items()}


@torch.no_grad()
def pose_contour_rms(fit: SilhouetteFit, full: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unweighted contour errors of every posture at ``full`` (B, P).

    Returns:
        ``(rms, e_m)``, each (B, J) image pixels in ``fit.poses`` order: the RMS distance of
        the person's contour pixels to the model contour (e_P) and e_M, whatever the posture
        weights and the reference scale (``fit.image_scale``).
    """
    r = fit.residual(full, fit.select(full))
    rl = fit.residual_layout
    w = fit.pose_weights * fit.image_scale[:, None]
    rms = torch.stack([r[:, rl.e_p(j)].norm(dim=1) for j in fit.poses], 1) / w
    e_m = torch.stack([r[:, rl.e_m(j)] for j in fit.poses], 1) / w
    return rms, e_m


def pose_outliers(rms: torch.Tensor, k: float | None, min_px: float) -> torch.Tensor:
    """(B, J) bool: postures whose contour RMS disagrees with the subject's others.

    A posture is an outlier when ``rms > median + max(k * 1.4826 * MAD, min_px)`` over the
    subject's postures (a robust z-score; the floor keeps sub-pixel spreads of a good fit from
    flagging a posture a pixel off). At most half the postures (rounded down) can be outliers,
    the worst first, so the rule always leaves a majority. ``k = None`` flags none.
    """
    if k is None or rms.shape[1] < 3:
        return torch.zeros_like(rms, dtype=torch.bool)
    med = rms.median(dim=1, keepdim=True).values
    mad = (rms - med).abs().median(dim=1, keepdim=True).values
    excess = torch.clamp(k * 1.4826 * mad, min=min_px)
    flagged = rms > med + excess
    # keep only the worst floor(J / 2)
    order = rms.argsort(dim=1, descending=True).argsort(dim=1)
    return flagged & (order < rms.shape[1] // 2)
