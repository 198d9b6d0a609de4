"""How clearly the images show a quantity of the fitted body: pin it elsewhere and refit.

At a fitted point, pin a scalar function ``q`` of the parameters (a segment's ratio to the
height, say) at another value ``t`` and refit: the images' problem (no prior or known facts:
with them, a pin away from the prior's pull lets the images fit better at the prior's
expense), plus one residual ``(q(x) − t) / tolerance`` that holds ``q`` there. What the
images pay for it is how much higher their robust cost ``Σ ρ(r²)`` over the image residuals
(e_P and e_M of every posture; not the barrier, prior or facts) ends than in the same refit
without the pin (a control: the fit it starts from may not be quite converged). An e_P block
sums to the mean squared contour distance of its posture, so 1 is as much as every contour
pixel of one posture moving one pixel further from the model.

The refit is nonlinear on purpose: a Gauss–Newton (linearised) estimate of the same rise is
fooled by the directions the images do not see to first order. A limb's length along the
line of sight is one: flexing a lengthened arm towards the camera keeps its outline, and the
linear model lets a 2 % longer arm span cost 0.07 where the nonlinear path costs 6.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import torch

from torchfit.fit.problem import SilhouetteFit
from torchfit.fit.stages import StageOptions, solve_stage
from torchfit.solver import LMOptions
from torchfit.solver.robust import robust_cost

__all__ = ["PinnedFit", "image_cost", "pinning_cost"]

#: The pin's tolerance, as a share of the distance from the fit to the target: a pin far
#: stiffer than the images would dominate the solver's scaling and damping, and the refit
#: would pay any image cost to satisfy it.
PIN_SHARE = 0.05


class PinnedFit:
    """A fit problem with one more residual per subject, ``(q(x) − target) / tolerance``.

    Everything else (posture residuals, barrier, prior, known facts) is the wrapped problem's.

    Args:
        fit: the problem (a :class:`SilhouetteFit` or a subclass).
        quantity: ``(full, rows)``: (N, P) parameter rows of the subjects ``rows`` (N,) ->
            (N,) their pinned quantity, differentiable.
        target: (B,) the value each subject's quantity is pinned at (NaN: not pinned).
        tolerance: (B,) a deviation from the target that costs as much as ``Σ r² = 1``.
    """

    def __init__(
        self,
        fit: SilhouetteFit,
        quantity: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
        target: torch.Tensor,
        tolerance: torch.Tensor,
    ) -> None:
        self.fit = fit
        self.quantity = quantity
        self.target = target
        self.tolerance = tolerance

    def __getattr__(self, name: str):
        return getattr(self.fit, name)

    def _rows(self, full: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
        return torch.arange(full.shape[0], device=full.device) if rows is None else rows

    def pin_residual(self, full: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """(N, 1) the pin's residual."""
        target = self.target[rows]
        free = torch.isnan(target)
        q = self.quantity(full, rows)
        r = (q - torch.where(free, q.detach(), target)) / self.tolerance[rows]
        return torch.where(free, torch.zeros_like(r), r)[:, None]

    def residual(self, full, selections=None, rows=None) -> torch.Tensor:
        """(N, M + 1): the problem's residuals, then the pin."""
        rows = self._rows(full, rows)
        base = self.fit.residual(full, selections, rows)
        return torch.cat([base, self.pin_residual(full, rows)], 1)

    def jacobian(self, full, free, selections, rows=None) -> torch.Tensor:
        """(N, M + 1, F): the problem's Jacobian, then the pin's row (reverse mode)."""
        rows = self._rows(full, rows)
        jac = self.fit.jacobian(full, free, selections, rows)
        x = full.detach().clone().requires_grad_(True)
        with torch.enable_grad():
            (grad,) = torch.autograd.grad(self.pin_residual(x, rows).sum(), x)
        return torch.cat([jac, grad[:, None, free]], 1)

    def loss_units(self) -> torch.Tensor:
        """The problem's, and the pin stays least squares."""
        units = self.fit.loss_units()
        return torch.cat([units, torch.full_like(units[:, :1], torch.inf)], 1)

    def residual_mask(self) -> torch.Tensor:
        """The problem's, and the pin is always valid."""
        mask = self.fit.residual_mask()
        return torch.cat([mask, mask.new_ones(mask.shape[0], 1)], 1)


@torch.no_grad()
def image_cost(fit: SilhouetteFit, full: torch.Tensor, loss: str, loss_scale: float):
    """(B,) ``Σ ρ(r²)`` of the image residuals (e_P, e_M) at ``full`` (B, P)."""
    r = fit.residual(full, fit.select(full))
    stop = fit.residual_layout.barrier.start
    units = fit.loss_units()[:, :stop]
    return 2 * robust_cost(r[:, :stop], loss, loss_scale, units)


def pinning_cost(
    fit: SilhouetteFit,
    full: torch.Tensor,
    stage: StageOptions,
    quantity: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    target: torch.Tensor,
    options: LMOptions,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The images' cost after refitting with each row's quantity pinned at its target.

    Args:
        fit: the problem, one row per pin (``fit.subset([i, i, ...])`` pins several
            quantities of subject ``i``), and a control row per subject with a NaN target.
        full: (B, P) fitted parameters.
        stage: the stage whose free parameters the refit moves (the fit's last).
        quantity: ``(full, rows)`` -> (N,) quantities, differentiable (see :class:`PinnedFit`).
        target: (B,) where to pin them; NaN: a free refit (the control).
        options: the refit's solver options (its loss is the one the costs are measured in).

    Returns:
        ``(cost, reached)``, each (B,): the images' robust cost ``Σ ρ(r²)`` at the refit, and
        the quantity there (near the target: the pin's tolerance is :data:`PIN_SHARE` of the
        way). What a pin costs the images is its row's cost minus its control's.
    """
    if stage.loss is not None:
        options = replace(options, loss=stage.loss)
    # every row runs all its iterations: a control that stops at once (its start meets the
    # tolerances) would be compared with pinned rows that went on descending
    options = replace(options, ftol=1e-15, xtol=1e-15, gtol=1e-15)
    with torch.no_grad():
        start = quantity(full, torch.arange(full.shape[0], device=full.device))
    tolerance = (PIN_SHARE * (target - start).abs()).nan_to_num(1.0).clamp_min(1e-6)
    x, _ = solve_stage(PinnedFit(fit, quantity, target, tolerance), full, stage, options)
    with torch.no_grad():
        reached = quantity(x, torch.arange(x.shape[0], device=x.device))
    return image_cost(fit, x, options.loss, options.loss_scale), reached
