"""The first paper's own formulation, kept as the baseline the autograd fit is measured against.

Each residual evaluation renders the model silhouette, follows its outer contour,
chamfer-transforms that contour (Borgefors 3-4) and samples: e_P at the person's contour
pixels in the model's distance map, e_M as the RMS of the person's distance map at the model's
contour pixels. Everything is integer pixels, so the residual is piecewise constant in the
parameters; the Jacobian is taken by forward differences with a step large enough to move the
contour (MINPACK's ``epsfcn``) and the problem is solved by MINPACK's ``lmdif``
(``scipy.optimize.leastsq`` without ``Dfun``), one subject at a time.

The residual vector has exactly the layout (and mask) of
:meth:`torchfit.fit.SilhouetteFit.residual`, so costs compare one to one.
"""

from __future__ import annotations

import torch

from torchfit.fit.problem import SilhouetteFit
from torchfit.fit.residuals import NO_CONTOUR_PENALTY, person_to_model
from torchfit.fit.stages import StageOptions
from torchfit.image.contours import trace_outer_contour
from torchfit.image.distance import distance_map
from torchfit.image.morphology import largest_component
from torchfit.solver import LMOptions
from torchfit.viz.raster import render_silhouette

__all__ = ["rendered_residual", "minpack_stage", "DEFAULT_EPSFCN"]

#: forward-difference step of the baseline: sqrt(1e-4) = 1 % of each parameter (or 0.01 for
#: parameters near zero), which moves the rendered contour by a few pixels
DEFAULT_EPSFCN = 1e-4


def _outer_contour_mask(mask) -> tuple[torch.Tensor, torch.Tensor]:
    """Ordered outer contour pixels (N, 2) of the largest blob and its (1, 1, H, W) mask."""
    contour = trace_outer_contour(largest_component(mask))  # (0, 2) for an empty mask
    seeds = torch.zeros(1, 1, *mask.shape, dtype=torch.bool)
    seeds[0, 0, contour[:, 1], contour[:, 0]] = True
    return contour, seeds


@torch.no_grad()
def rendered_residual(fit: SilhouetteFit, full: torch.Tensor) -> torch.Tensor:
    """The paper's residual by rendering, for parameters ``full`` (B, P).

    Returns:
        (B, M) residuals laid out as :meth:`SilhouetteFit.residual` (padding entries zero).
    """
    b = full.shape[0]
    rows = torch.arange(b, device=full.device)
    faces = fit.model.faces.cpu().numpy()
    size = fit.camera.image_size
    parts = []
    for k, j in enumerate(fit.poses):
        pixels = fit.pose_pixels(full, j, rows).cpu().double().numpy()
        contour_p = fit.person.contours[k].long()
        valid = fit.person.valid[k]
        e_p = torch.zeros(b, contour_p.shape[1], dtype=full.dtype)
        e_m = torch.full((b,), NO_CONTOUR_PENALTY, dtype=full.dtype)
        for i in range(b):
            model_contour, seeds = _outer_contour_mask(render_silhouette(pixels[i], faces, size))
            if len(model_contour) == 0:
                e_p[i] = float(size[0] + size[1])
                continue
            d_model = distance_map(seeds, "chamfer")[0, 0].double()
            u = contour_p[i, :, 0].clamp(0, size[0] - 1)
            v = contour_p[i, :, 1].clamp(0, size[1] - 1)
            e_p[i] = d_model[v, u].to(full.dtype)
            d_person = fit.person.distance_maps[k][i].double()
            at = d_person[model_contour[:, 1], model_contour[:, 0]]
            e_m[i] = torch.sqrt((at * at).mean()).to(full.dtype)
        parts.append(torch.cat([person_to_model(e_p, valid), e_m[:, None]], dim=1))
    parts.append(fit.barrier_residual(full))
    return torch.cat(parts, dim=1)


def minpack_stage(
    fit: SilhouetteFit,
    full: torch.Tensor,
    stage: StageOptions,
    options: LMOptions,
    epsfcn: float = DEFAULT_EPSFCN,
):
    """One stage of the fit by the baseline: rendered residual, MINPACK lmdif per subject.

    Returns:
        (B, P) parameters after the stage and one :class:`~torchfit.solver.LMResult` (batch
        of 1) per subject.
    """
    from torchfit.solver import minpack_baseline

    free = fit.stage_indices(list(stage.scales), stage.joints, stage.root)
    out = full.detach().clone()
    results = []
    for i in range(full.shape[0]):
        one = fit.subset([i])
        base = full[i : i + 1].detach().clone()

        def residual_fn(x: torch.Tensor, one=one, base=base) -> torch.Tensor:
            params = base.expand(x.shape[0], -1).clone()
            params[:, free] = x
            return rendered_residual(one, params)

        res = minpack_baseline(residual_fn, base[:, free], options, epsfcn=epsfcn)
        out[i, free] = res.x[0]
        results.append(res)
    return out, results
