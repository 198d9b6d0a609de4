"""The damped systems' Cholesky factor and solve: a problem's values in a batch are the ones it
has alone, bit for bit (MKL rounds by the data's memory alignment, which a matrix's offset in
a batched tensor changes; the tracker's 49 and the fit's 147 parameters are sizes where a
batched call rounds a problem differently on this machine's build)."""

import pytest
import torch

from torchfit.solver.normal import cholesky_each, cholesky_solve_each


@pytest.mark.parametrize("p", [49, 147])
def test_each_problem_is_factored_and_solved_as_alone(p):
    g = torch.Generator().manual_seed(0)
    mats = []
    for _ in range(3):
        a = torch.randn(p, p + 5, generator=g, dtype=torch.float64)
        mats.append(a @ a.T + 1e-3 * torch.eye(p, dtype=torch.float64))
    batch = torch.stack(mats)
    rhs = torch.randn(3, p, generator=g, dtype=torch.float64)
    factor, info = cholesky_each(batch)
    h = cholesky_solve_each(rhs, factor)
    assert info.tolist() == [0, 0, 0]
    for b in range(3):
        alone, _ = torch.linalg.cholesky_ex(mats[b].clone())
        assert torch.equal(factor[b], alone)
        assert torch.equal(h[b], torch.cholesky_solve(rhs[b, :, None].clone(), alone)[:, 0])
    # and they solve the systems
    torch.testing.assert_close(torch.linalg.solve(batch, rhs), h, rtol=1e-8, atol=1e-8)


def test_a_matrix_that_is_not_positive_definite_is_reported_in_its_own_row():
    good = torch.eye(4, dtype=torch.float64)
    bad = -torch.eye(4, dtype=torch.float64)
    _, info = cholesky_each(torch.stack([good, bad, good]))
    assert info.tolist()[0] == 0 and info.tolist()[1] > 0 and info.tolist()[2] == 0
