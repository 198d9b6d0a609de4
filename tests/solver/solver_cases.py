"""Shared helpers of the solver tests: a mixed batch of small problems with per-problem data."""

from __future__ import annotations

import torch

# Each problem has P = 2 parameters and M = 3 residuals; its kind selects the formula.
EASY, HARD, DIVERGING, NAN = 0, 1, 2, 3


def _easy(x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    # Nearly linear: minimum at x = c.
    d = x - c
    return torch.stack([d[:, 0], d[:, 1], 0.1 * d[:, 0] * d[:, 1]], dim=1)


def _hard(x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    # Rosenbrock with a shifted valley, plus a third residual that vanishes at the minimum.
    a = x[:, 0] - c[:, 0]
    return torch.stack([10 * (x[:, 1] - a * a), 1 - a, 0.5 * (1 - a) * x[:, 1]], dim=1)


def _diverging(x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    # No minimiser: the cost only tends to c² as x grows.
    return torch.stack([torch.exp(-x[:, 0]), torch.exp(-x[:, 1]), c[:, 0] + 0 * x[:, 0]], dim=1)


def _nan(x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    # sqrt of a quantity that the Gauss-Newton step drives negative: NaN trial residuals.
    return torch.stack(
        [torch.sqrt(x[:, 0]) + c[:, 0], torch.sqrt(x[:, 1]) - c[:, 1], x[:, 0] - x[:, 1]], dim=1
    )


_FORMULAS = {EASY: _easy, HARD: _hard, DIVERGING: _diverging, NAN: _nan}


def make_mixed(kinds: list[int], data: torch.Tensor):
    """A residual function for problems of the given kinds with per-problem data ``(B, 2)``.

    Follows the solver's folding contract: an input of ``K * B`` rows holds ``K`` copies of the
    batch, row ``i`` belonging to problem ``i % B``.
    """
    batch = len(kinds)
    kinds_t = torch.tensor(kinds)

    def residual(x: torch.Tensor) -> torch.Tensor:
        k = x.shape[0] // batch
        kind_rows = kinds_t.repeat(k)
        c = data.repeat(k, 1)
        out = []
        order = []
        for kind, formula in _FORMULAS.items():
            rows = torch.nonzero(kind_rows == kind).flatten()
            if rows.numel():
                out.append(formula(x.index_select(0, rows), c.index_select(0, rows)))
                order.append(rows)
        perm = torch.cat(order)
        inverse = torch.empty_like(perm)
        inverse[perm] = torch.arange(perm.numel())
        return torch.cat(out).index_select(0, inverse)

    return residual
