"""The fit's Jacobian and residual in one pass (:meth:`torchfit.fit.problem.SilhouetteFit.
jacobian_and_residual`).

Per posture, two derivatives meet at the projected contour vertices: the vertices' pixel
derivatives w.r.t. the parameters the posture depends on (the scales and its own), in closed
form (:meth:`torchfit.fit.pose.Poser.world_jacobian` through
:func:`torchfit.camera.project_with_jacobian`), and every residual entry's derivative w.r.t. the
pixels of its own edge endpoints, by reverse mode. Their product is the posture's block; the
reverse-mode pass's values are the residual.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from torchfit.camera import project_with_jacobian
from torchfit.fit.residuals import padded_row_sum

if TYPE_CHECKING:
    from torchfit.fit.model_contour import ContourSelection
    from torchfit.fit.problem import SilhouetteFit

__all__ = ["ENDPOINTS", "jacobian_and_residual"]

#: The endpoint pixels of a residual entry and the ContourEndpoints field naming their vertex.
ENDPOINTS = {"pa": "person_a", "pb": "person_b", "ma": "model_a", "mb": "model_b"}


def jacobian_and_residual(
    fit: SilhouetteFit,
    full: torch.Tensor,
    free: torch.Tensor,
    selections: dict[int, ContourSelection],
    rows: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, M, F) Jacobian of ``fit.residual`` w.r.t. the ``free`` (F,) parameters and the
    (N, M) residual, at parameter rows ``full`` (N, P) of the subjects ``rows`` (N,) (default:
    row i is subject i) with the contour choice ``selections``."""
    b = full.shape[0]
    f = free.numel()
    rl = fit.residual_layout
    jac = torch.zeros(b, rl.size, f, **fit.kw)
    at = torch.arange(b, device=full.device)
    if rows is None:
        rows = at
    scale_cols = (free < fit.layout.num_scale_params).nonzero().flatten()
    parts = []
    for k, j in enumerate(fit.poses):
        sel = selections[j]
        sl = fit.layout.blocks[j].columns
        pose_cols = ((free >= sl.start) & (free < sl.stop)).nonzero().flatten()
        cols = torch.cat([scale_cols, pose_cols])
        c = cols.numel()
        if c == 0:
            parts.append(fit.pose_residual(full, j, rows, sel))
            continue
        ends, vidx, lookup = fit._prepare(sel)
        # closed form: the contour vertices' pixels and their derivatives w.r.t. the
        # posture's columns, of which the free ones are kept
        world, d_world = fit.poser.world_jacobian(full, j, rows, vidx)
        local_cols = torch.searchsorted(fit.poser.columns(j).to(free.device), free[cols])
        pixels, d_pix = project_with_jacobian(world, d_world[..., local_cols], fit.camera[rows])
        # (B K, 2, c): each vertex's pixel derivatives as one contiguous row
        flat = d_pix.reshape(-1, 2, c)
        # reverse mode: local derivatives of the residual entries w.r.t. endpoint pixels
        pix = {
            n: v.detach().requires_grad_(True)
            for n, v in fit._endpoint_pixels(pixels, lookup, ends).items()
        }
        with torch.enable_grad():
            e_p, e_m = fit._pose_terms(k, rows, ends, sel, pix)
            grads = torch.autograd.grad(
                e_p.sum() + e_m.sum(), list(pix.values()), allow_unused=True
            )
        local = {
            n: (g if g is not None else torch.zeros_like(pix[n]))
            for n, g in zip(pix, grads, strict=True)
        }
        # each entry's endpoint as a row of ``flat``
        first = (at * pixels.shape[1])[:, None]
        at_row = {n: first + lookup[getattr(ends, a)] for n, a in ENDPOINTS.items()}
        # Products and sums written out, not einsum (batched products round a subject's
        # row by batch size); the model-contour sum ignores padding (padded_row_sum).
        block_p = _chain(local["pa"], flat, at_row["pa"]) + _chain(local["pb"], flat, at_row["pb"])
        per_point = _chain(local["ma"], flat, at_row["ma"]) + _chain(
            local["mb"], flat, at_row["mb"]
        )
        block_m = padded_row_sum(per_point.transpose(1, 2))
        weight = fit.image_weights(rows, k)
        parts.append(torch.cat([e_p.detach(), e_m.detach()[:, None]], 1) * weight)
        # the scale columns and the posture's own are two runs of consecutive columns
        e_p_rows, e_m_row = rl.e_p(j), rl.e_m(j)
        for run, part in _runs(cols, block_p * weight[:, :, None], block_m * weight):
            jac[:, e_p_rows, run] = part[0]
            jac[:, e_m_row, run] = part[1]
    # barrier: elementwise, derivative weight * (-1 below, +1 above, 0 inside)
    x = full[:, free]
    lo, hi = fit.lower[free], fit.upper[free]
    slope = fit.options.barrier_weight * ((x > hi).to(x) - (x < lo).to(x))
    jac[:, rl.barrier.start + free, torch.arange(f)] = slope
    parts.append(fit.barrier_residual(full))
    return jac, torch.cat(parts, 1)


def _chain(local: torch.Tensor, flat: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(B, n, c): each entry's derivative w.r.t. its endpoint pixel (B, n, 2) times that
    endpoint's pixel tangents, rows ``index`` (B, n) of ``flat`` (B K, 2, c)."""
    tangents = flat.index_select(0, index.flatten()).reshape(*index.shape, 2, -1)
    return local[..., 0, None] * tangents[:, :, 0] + local[..., 1, None] * tangents[:, :, 1]


def _runs(cols: torch.Tensor, block_p: torch.Tensor, block_m: torch.Tensor):
    """Split the columns ``cols`` (c,) into runs of consecutive values: yields (slice of the
    Jacobian's columns, (block_p[..., part], block_m[..., part])) per run."""
    values = cols.tolist()
    start = 0
    for i in range(1, len(values) + 1):
        if i == len(values) or values[i] != values[i - 1] + 1:
            part = slice(start, i)
            yield slice(values[start], values[i - 1] + 1), (block_p[..., part], block_m[..., part])
            start = i
