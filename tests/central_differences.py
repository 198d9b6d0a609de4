"""The fitting problem's residual differentiated by central differences, for checking the
Jacobian rows a problem computes. Kept beside the tests that use it."""

from __future__ import annotations

import torch


def residual_differences(fit, x, selections, rows, columns, h: float = 1e-6) -> torch.Tensor:
    """(B, R, C) central differences of ``fit.residual(x, selections)[:, rows]`` w.r.t. the
    parameter columns ``columns`` (C,), the contour choice held at ``selections``."""
    out = []
    for p in [int(c) for c in columns]:
        plus, minus = x.clone(), x.clone()
        plus[:, p] += h
        minus[:, p] -= h
        out.append((fit.residual(plus, selections) - fit.residual(minus, selections))[:, rows])
    return torch.stack(out, -1) / (2 * h)


def perturbed_start(fit, scale: float, seed: int) -> torch.Tensor:
    """(1, P) the problem's start moved by ``scale`` times seeded normal noise."""
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(1, fit.num_params, generator=g, dtype=torch.float64)
    return fit.initial_params() + scale * noise
