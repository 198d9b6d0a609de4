"""Block-sparse normal equations (``jacobian_blocks``): the same JᵀJ and Jᵀr as the dense
product on a Jacobian with that sparsity, the same bits for a problem alone or in a batch,
checked blocks, and a solve that takes the same steps as without them."""

from __future__ import annotations

import pytest
import torch

from torchfit.solver import LMOptions, SolverError, levenberg_marquardt
from torchfit.solver.normal import normal_equations, valid_entries


def _sparse_jacobian(batch: int, seed: int):
    """(B, 30, 7): rows 0-11 depend on columns 0-3, rows 12-23 on 0, 1, 4, 5, rows 24-29
    (outside every block) on all; padding rows 10-11 and 20-23 invalid for some problems."""
    g = torch.Generator().manual_seed(seed)
    jac = torch.randn(batch, 30, 7, generator=g, dtype=torch.float64)
    jac[:, :12, 4:] = 0
    jac[:, 12:24, 2:4] = 0
    jac[:, 12:24, 6] = 0
    r = torch.randn(batch, 30, generator=g, dtype=torch.float64)
    mask = torch.ones(batch, 30, dtype=torch.bool)
    mask[0, 10:12] = False
    mask[-1, 20:24] = False
    jac[~mask] = 0
    r[~mask] = 0
    blocks = [
        (slice(0, 12), torch.tensor([0, 1, 2, 3])),
        (slice(12, 24), torch.tensor([0, 1, 4, 5])),
    ]
    return jac, r, mask, blocks


def test_block_normal_equations_equal_the_dense_ones():
    jac, r, mask, blocks = _sparse_jacobian(3, seed=0)
    valid = valid_entries(mask, 3)
    a_dense, g_dense = normal_equations(jac, r, valid)
    a_block, g_block = normal_equations(jac, r, valid, blocks)
    torch.testing.assert_close(a_block, a_dense, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(g_block, g_dense, rtol=1e-12, atol=1e-12)
    # a block that claims too few columns drops real terms: the blocks are trusted
    wrong = [(slice(0, 12), torch.tensor([0, 1, 2])), blocks[1]]
    a_wrong, _ = normal_equations(jac, r, valid, wrong)
    assert float((a_wrong - a_dense).abs().max()) > 1e-3


def test_block_normal_equations_of_a_problem_do_not_depend_on_its_batch():
    jac, r, mask, blocks = _sparse_jacobian(4, seed=1)
    valid = valid_entries(mask, 4)
    a_all, g_all = normal_equations(jac, r, valid, blocks)
    for b in range(4):
        a_one, g_one = normal_equations(jac[b : b + 1], r[b : b + 1], valid[b : b + 1], blocks)
        assert torch.equal(a_one[0], a_all[b]) and torch.equal(g_one[0], g_all[b])


def test_overlapping_or_outside_blocks_are_refused():
    jac, r, mask, _ = _sparse_jacobian(1, seed=2)
    with pytest.raises(ValueError, match="overlap"):
        normal_equations(jac, r, valid_entries(mask, 1), [(slice(0, 12), torch.arange(7))] * 2)

    def fn(x):
        return torch.cat([x, x**2], 1)

    x0 = torch.ones(1, 3, dtype=torch.float64)
    with pytest.raises(SolverError, match="jacobian_blocks"):
        levenberg_marquardt(fn, x0, jacobian_blocks=[(slice(0, 9), torch.arange(3))])
    with pytest.raises(SolverError, match="jacobian_blocks"):
        levenberg_marquardt(fn, x0, jacobian_blocks=[(slice(0, 3), torch.tensor([0, 3]))])


def test_a_solve_with_blocks_follows_the_dense_solve():
    """Two independent sub-problems in one residual: rows 0-2 on x0, x1; rows 3-5 on x2, x3;
    the same steps (to rounding) as the dense normal equations."""

    def fn(x):
        x0, x1, x2, x3 = x.unbind(1)
        a = torch.stack([x0 - 0.5, x1 + 1.0, x0 * x1 + 0.5], 1)
        b = torch.stack([x2 - 2.0, torch.exp(x3) - torch.exp(torch.tensor(0.3)), x2 * x3 - 0.6], 1)
        return torch.cat([a, b], 1)

    x0 = torch.tensor([[1.0, 1.0, 1.0, 1.0]], dtype=torch.float64)
    blocks = [(slice(0, 3), torch.tensor([0, 1])), (slice(3, 6), torch.tensor([2, 3]))]
    dense = levenberg_marquardt(fn, x0, LMOptions(max_iter=30))
    sparse = levenberg_marquardt(fn, x0, LMOptions(max_iter=30), jacobian_blocks=blocks)
    torch.testing.assert_close(sparse.x, dense.x, rtol=0, atol=1e-10)
    target = torch.tensor([[0.5, -1.0, 2.0, 0.3]], dtype=torch.float64)
    torch.testing.assert_close(sparse.x, target, rtol=0, atol=1e-6)


def test_valid_entries_are_each_problems_own_ascending_indices():
    g = torch.Generator().manual_seed(3)
    mask = torch.rand(6, 40, generator=g) > 0.5
    mask[1] = False  # a problem with no valid entry
    mask[4] = True
    got = valid_entries(mask, 6)
    assert len(got) == 6
    for row, idx in zip(mask, got, strict=True):
        assert idx.dtype == torch.long and torch.equal(idx, torch.arange(40)[row])
    assert got[1].numel() == 0 and got[4].numel() == 40
    assert valid_entries(None, 3) == [None, None, None]
