"""The active set: finished problems leave the batch, and the batch leaks into no problem.

An indexed residual function (``indexed=True``) is called for the running problems only, so a
problem that converges or fails is not evaluated again; and a problem's iterates are bit for
bit those it has alone, whatever the batch's size, order or residual padding.
"""

from __future__ import annotations

from collections import Counter

import torch
from solver_cases import DIVERGING, EASY, HARD, NAN, make_mixed

from torchfit.solver import LMOptions, LMStatus, levenberg_marquardt

KINDS = [EASY, HARD, DIVERGING, NAN, HARD]
DATA = torch.tensor(
    [[1.0, -2.0], [0.5, 0.0], [2.0, 0.0], [1.0, 1.0], [-1.0, 0.0]], dtype=torch.float64
)
# Problem 0 starts at its minimum: it stops at the first gradient test.
X0 = torch.tensor(
    [[1.0, -2.0], [-1.2, 1.0], [0.0, 0.0], [4.0, 0.1], [-2.5, 2.0]], dtype=torch.float64
)
OPTS = LMOptions(max_iter=40, ftol=1e-14, xtol=1e-14, gtol=1e-14, max_bad_steps=4)


def counted(kinds: list[int], data: torch.Tensor, calls: Counter, width: int = 3):
    """An indexed residual of the mixed problems that counts the rows it gets per problem,
    its residual padded (and masked) to ``width`` entries."""
    plain = [make_mixed([k], data[i : i + 1]) for i, k in enumerate(kinds)]

    def residual(x: torch.Tensor, index: torch.Tensor):
        calls.update(index.tolist())
        rows = [plain[int(i)](x[n : n + 1]) for n, i in enumerate(index)]
        r = torch.cat(rows)
        pad = r.new_zeros(r.shape[0], width - 3)
        mask = torch.ones(r.shape[0], width, dtype=torch.bool)
        mask[:, 3:] = False
        return torch.cat([r, pad], 1), mask

    return residual


def test_a_finished_problem_is_not_evaluated_again_and_each_equals_it_alone():
    calls: Counter = Counter()
    batch = levenberg_marquardt(counted(KINDS, DATA, calls), X0, OPTS, indexed=True)
    assert batch.statuses[0] == LMStatus.GTOL and int(batch.n_iter[0]) == 0
    assert int(batch.n_iter[1]) > 5
    for b in range(len(KINDS)):
        alone_calls: Counter = Counter()
        fn = counted([KINDS[b]], DATA[b : b + 1], alone_calls, width=3 + b)  # other padding
        alone = levenberg_marquardt(fn, X0[b : b + 1], OPTS, indexed=True)
        # the same rows evaluated for it in the batch as alone: none after it finished
        assert calls[b] == alone_calls[0], (b, calls[b], alone_calls[0])
        torch.testing.assert_close(batch.x[b : b + 1], alone.x, rtol=0, atol=0)
        torch.testing.assert_close(batch.cost[b : b + 1], alone.cost, rtol=0, atol=0)
        for name in ("status", "n_iter", "nfev", "njev"):
            assert getattr(batch, name)[b] == getattr(alone, name)[0], (name, b)
    # the finished problem cost one evaluation and one Jacobian (P = 2 folded rows)
    assert calls[0] == 1 + 2


def test_any_order_of_the_batch_gives_the_same_answers():
    order = torch.tensor([4, 2, 0, 3, 1])
    kinds = [KINDS[i] for i in order]
    first = levenberg_marquardt(counted(KINDS, DATA, Counter()), X0, OPTS, indexed=True)
    again = levenberg_marquardt(
        counted(kinds, DATA[order], Counter(), width=7), X0[order], OPTS, indexed=True
    )
    torch.testing.assert_close(again.x, first.x[order], rtol=0, atol=0)
    assert torch.equal(again.status, first.status[order])


def test_a_plain_residual_function_gives_what_an_indexed_one_does():
    indexed = levenberg_marquardt(counted(KINDS, DATA, Counter()), X0, OPTS, indexed=True)
    plain = levenberg_marquardt(make_mixed(KINDS, DATA), X0, OPTS)
    torch.testing.assert_close(plain.x, indexed.x, rtol=0, atol=0)
    for name in ("status", "n_iter", "nfev", "njev"):
        assert torch.equal(getattr(plain, name), getattr(indexed, name)), name


def test_an_indexed_user_jacobian_gets_the_rows_it_is_asked_for():
    seen: list[list[int]] = []
    fn = counted(KINDS, DATA, Counter())

    def jac(x: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        seen.append(index.tolist())
        cols = []
        for k in range(x.shape[1]):
            h = torch.zeros_like(x)
            h[:, k] = 1e-7
            cols.append((fn(x + h, index)[0] - fn(x, index)[0]) / 1e-7)
        return torch.stack(cols, dim=2)

    res = levenberg_marquardt(fn, X0, OPTS, jacobian=jac, indexed=True)
    assert seen[0] == [0, 1, 2, 3, 4]
    assert all(0 not in rows for rows in seen[1:])  # problem 0 finished at once
    assert bool((res.status > 0).all())


def _tanh_problem(n: int, p: int = 24):
    """A(n, p), y(n), x0(p) of ``r(x) = tanh(A x) - y``, the same for the same ``n``."""
    g = torch.Generator().manual_seed(n)
    a = torch.randn(n, p, generator=g, dtype=torch.float64) / p**0.5
    y = 0.5 * torch.tanh(torch.randn(n, generator=g, dtype=torch.float64))
    return a, y, torch.randn(p, generator=g, dtype=torch.float64)


def _padded(sizes: list[int], width: int):
    """A plain residual function of the problems ``sizes`` padded (and masked) to ``width``,
    and their starts ``(B, P)``; large enough that batched products round by batch size."""
    problems = [_tanh_problem(n) for n in sizes]

    def residual(x: torch.Tensor):
        out = x.new_zeros(x.shape[0], width)
        mask = torch.zeros(x.shape[0], width, dtype=torch.bool)
        for b, (a, y, _) in enumerate(problems):
            rows = torch.arange(b, x.shape[0], len(sizes))  # folded copies of problem b
            out[rows, : len(y)] = torch.tanh(x[rows] @ a.T) - y
            mask[rows, : len(y)] = True
        return out, mask

    return residual, torch.stack([x0 for _, _, x0 in problems])


def test_padding_and_batch_size_do_not_change_the_rounding():
    sizes = [1630, 1100, 700]
    opts = LMOptions(max_iter=4)
    fn, x0 = _padded(sizes, 1700)
    batch = levenberg_marquardt(fn, x0, opts, jacobian="forward")
    for b, n in enumerate(sizes):
        fn_b, x0_b = _padded([n], n)
        alone = levenberg_marquardt(fn_b, x0_b, opts, jacobian="forward")
        torch.testing.assert_close(batch.x[b : b + 1], alone.x, rtol=0, atol=0)
        torch.testing.assert_close(batch.cost[b : b + 1], alone.cost, rtol=0, atol=0)
