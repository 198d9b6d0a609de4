"""Tests of torchfit.fit.residuals (e_P, e_M, e_B).

Reference: the paper's formulas evaluated by hand for small cases and by a naive Python loop
over rows and contour points for random batches; gradients by ``torch.autograd.gradcheck``
(float64 central differences).
"""

from __future__ import annotations

import math

import pytest
import torch

from torchfit.fit.residuals import NO_CONTOUR_PENALTY, barrier, model_to_person, person_to_model


def _loop_person_to_model(distances: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    out = torch.zeros_like(distances)
    for b in range(distances.shape[0]):
        n = sum(bool(v) for v in valid[b])
        for c in range(distances.shape[1]):
            if valid[b, c]:
                out[b, c] = float(distances[b, c]) / math.sqrt(n)
    return out


def _loop_model_to_person(distances: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    out = []
    for b in range(distances.shape[0]):
        vals = [float(d) for d, v in zip(distances[b], valid[b], strict=True) if v]
        out.append(math.sqrt(sum(d * d for d in vals) / len(vals)) if vals else NO_CONTOUR_PENALTY)
    return torch.tensor(out, dtype=distances.dtype)


def test_person_to_model_hand_computed():
    d = torch.tensor([[3.0, 4.0, 99.0, 12.0], [2.0, -7.0, 5.0, 1.0]], dtype=torch.float64)
    valid = torch.tensor([[True, True, False, True], [True, False, False, False]])
    e = person_to_model(d, valid)
    # row 0: 3 valid pixels -> divide by sqrt(3); row 1: 1 valid -> unchanged; padding -> 0
    s3 = math.sqrt(3.0)
    expected = torch.tensor([[3 / s3, 4 / s3, 0.0, 12 / s3], [2.0, 0.0, 0.0, 0.0]], dtype=d.dtype)
    torch.testing.assert_close(e, expected)
    # sum of squares is the mean squared distance over the valid pixels
    torch.testing.assert_close((e[0] ** 2).sum(), torch.tensor((9 + 16 + 144) / 3, dtype=d.dtype))


def test_person_to_model_matches_loop_and_ignores_padding_values():
    g = torch.Generator().manual_seed(0)
    d = torch.rand(5, 9, generator=g, dtype=torch.float64) * 20
    valid = torch.rand(5, 9, generator=g) > 0.4
    valid[3] = False  # an empty row: all zero, no division by zero
    e = person_to_model(d, valid)
    torch.testing.assert_close(e, _loop_person_to_model(d, valid))
    assert torch.equal(e[3], torch.zeros(9, dtype=d.dtype))
    garbage = torch.where(valid, d, torch.full_like(d, 1e6))
    torch.testing.assert_close(person_to_model(garbage, valid), e)


def test_model_to_person_hand_computed():
    d = torch.tensor([[3.0, 4.0, 50.0], [6.0, 0.0, 0.0]], dtype=torch.float64)
    valid = torch.tensor([[True, True, False], [True, False, False]])
    e = model_to_person(d, valid)
    # row 0: sqrt((9 + 16) / 2); row 1: sqrt(36) (up to the 1e-12 smooth floor)
    expected = torch.tensor([math.sqrt(12.5), 6.0], dtype=d.dtype)
    torch.testing.assert_close(e, expected, atol=1e-9, rtol=0)
    assert e.shape == (2,)


def test_model_to_person_no_contour_penalty_and_perfect_fit():
    d = torch.tensor([[1.0, 2.0], [0.0, 0.0], [5.0, 5.0]], dtype=torch.float64)
    valid = torch.tensor([[False, False], [True, True], [True, False]])
    e = model_to_person(d, valid)
    assert NO_CONTOUR_PENALTY == 1e3
    assert float(e[0]) == NO_CONTOUR_PENALTY  # nothing valid: the large constant
    # a perfect fit is sqrt(1e-12) = 1e-6, not 0, so its derivative stays finite
    torch.testing.assert_close(e[1], torch.tensor(1e-6, dtype=d.dtype), atol=1e-12, rtol=0)
    torch.testing.assert_close(e[2], torch.tensor(5.0, dtype=d.dtype))
    x = d.clone().requires_grad_()
    model_to_person(x, valid).sum().backward()
    assert torch.isfinite(x.grad).all()
    assert torch.equal(x.grad[0], torch.zeros(2, dtype=d.dtype))  # penalty is a constant
    torch.testing.assert_close(x.grad[2], torch.tensor([1.0, 0.0], dtype=d.dtype))


def test_model_to_person_matches_loop():
    g = torch.Generator().manual_seed(1)
    d = torch.randn(6, 11, generator=g, dtype=torch.float64) * 4
    valid = torch.rand(6, 11, generator=g) > 0.5
    valid[2] = False
    valid[4] = True
    torch.testing.assert_close(model_to_person(d, valid), _loop_model_to_person(d, valid))


def test_residual_gradients_gradcheck():
    g = torch.Generator().manual_seed(2)
    d = (torch.rand(3, 7, generator=g, dtype=torch.float64) * 5 + 0.5).requires_grad_()
    valid = torch.rand(3, 7, generator=g) > 0.3
    valid[:, 0] = True
    assert torch.autograd.gradcheck(lambda x: person_to_model(x, valid), (d,))
    assert torch.autograd.gradcheck(lambda x: model_to_person(x, valid), (d,))
    # analytic: d e_M / d d_j = d_j / (n e_M) on valid points
    x = d.detach().clone().requires_grad_()
    e = model_to_person(x, valid)
    e.sum().backward()
    n = valid.sum(1, keepdim=True).to(x.dtype)
    expected = torch.where(valid, x.detach() / (n * e.detach()[:, None]), torch.zeros_like(x))
    torch.testing.assert_close(x.grad, expected)


def test_barrier_inside_below_above():
    x = torch.tensor([[0.5, -1.0, 3.0, 2.0, 0.0]], dtype=torch.float64)
    lower = torch.tensor([0.0, 0.0, 0.0, -math.inf, 0.0], dtype=torch.float64)
    upper = torch.tensor([1.0, 1.0, 1.0, math.inf, 0.0], dtype=torch.float64)
    e = barrier(x, lower, upper, 2.0)
    # inside -> 0; 1 below -> 2*1; 2 above -> 2*2; unbounded -> 0; on a degenerate interval -> 0
    torch.testing.assert_close(e, torch.tensor([[0.0, 2.0, 4.0, 0.0, 0.0]], dtype=x.dtype))
    # exactly on the bounds is inside
    on = barrier(torch.tensor([[0.0, 1.0]]), torch.zeros(2), torch.ones(2), 5.0)
    assert torch.equal(on, torch.zeros(1, 2))


def test_barrier_matches_loop_with_batched_bounds_and_tensor_weight():
    g = torch.Generator().manual_seed(3)
    x = torch.randn(4, 6, generator=g, dtype=torch.float64) * 3
    lower = torch.randn(4, 6, generator=g, dtype=torch.float64) - 1
    upper = lower + torch.rand(4, 6, generator=g, dtype=torch.float64) * 2
    weight = torch.tensor(0.7, dtype=torch.float64)
    expected = torch.zeros_like(x)
    for b in range(4):
        for p in range(6):
            xi, lo, hi = float(x[b, p]), float(lower[b, p]), float(upper[b, p])
            expected[b, p] = 0.7 * (max(0.0, lo - xi) + max(0.0, xi - hi))
    torch.testing.assert_close(barrier(x, lower, upper, weight), expected)
    assert (expected > 0).any() and (expected == 0).any()  # both regimes exercised


def test_barrier_gradients():
    lower = torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64)
    upper = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)
    # away from the kinks at the bounds: below, inside, above
    x = torch.tensor([[-0.5, 0.4, 1.7]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: barrier(v, lower, upper, 3.0), (x,))
    barrier(x, lower, upper, 3.0).sum().backward()
    torch.testing.assert_close(x.grad, torch.tensor([[-3.0, 0.0, 3.0]], dtype=x.dtype))
    # and with respect to the bounds themselves
    lo = lower.clone().requires_grad_()
    hi = upper.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda a, b: barrier(x.detach(), a, b, 3.0), (lo, hi))


@pytest.mark.parametrize("fn", [person_to_model, model_to_person])
def test_float32_keeps_dtype(fn):
    d = torch.tensor([[1.0, 2.0]], dtype=torch.float32)
    assert fn(d, torch.tensor([[True, True]])).dtype == torch.float32


def test_padded_row_sum_ignores_padding_and_memory_layout():
    """The same terms give the same sums bit for bit: alone, zero-padded to a longer row (a
    batch's longest), and as a strided view (the Jacobian sums a transposed tensor). Reference:
    the row alone, contiguous, through the same function."""
    from torchfit.fit.residuals import SUM_CHUNK, padded_row_sum

    gen = torch.Generator().manual_seed(0)
    n = 27 * SUM_CHUNK - 44  # not a whole number of chunks: padded inside the function
    values = torch.randn(57, n, generator=gen, dtype=torch.float64) * 1e3
    alone = padded_row_sum(values)
    padded = torch.cat([values, torch.zeros(57, 44, dtype=torch.float64)], 1)  # whole chunks
    strided = padded.T.contiguous().T  # the same numbers, last dimension not contiguous
    assert not strided.is_contiguous()
    assert torch.equal(padded_row_sum(padded), alone)
    assert torch.equal(padded_row_sum(strided), alone)
    # and a plain sum would not have been invariant here (otherwise this test proves nothing)
    assert torch.allclose(padded.sum(-1), alone, rtol=0, atol=1e-9)
