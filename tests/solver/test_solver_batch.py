"""Per-problem state: a batch gives the iterates of each problem solved alone."""

from __future__ import annotations

import pytest
import torch
from solver_cases import DIVERGING, EASY, HARD, NAN, make_mixed

from torchfit.solver import LMIterate, LMOptions, LMStatus, SolverError, levenberg_marquardt

KINDS = [EASY, HARD, DIVERGING, NAN, HARD, EASY, NAN]
DATA = torch.tensor(
    [[1.0, -2.0], [0.5, 0.0], [2.0, 0.0], [1.0, 1.0], [-1.0, 0.0], [3.0, 4.0], [0.5, 2.0]],
    dtype=torch.float64,
)
X0 = torch.tensor(
    [[0.0, 0.0], [-1.2, 1.0], [0.0, 0.0], [4.0, 0.1], [-2.5, 2.0], [10.0, -3.0], [0.2, 5.0]],
    dtype=torch.float64,
)


def _record():
    log: list[LMIterate] = []
    return log, log.append


@pytest.mark.parametrize(
    ("jacobian", "accel"),
    [("autograd", False), ("reverse", False), ("numeric", False), ("autograd", True)],
)
def test_batch_equals_each_problem_alone(jacobian, accel):
    opts = LMOptions(
        max_iter=60,
        ftol=1e-14,
        xtol=1e-14,
        gtol=1e-14,
        max_bad_steps=4,
        geodesic_acceleration=accel,
    )
    log, cb = _record()
    batch = levenberg_marquardt(make_mixed(KINDS, DATA), X0, opts, jacobian=jacobian, callback=cb)
    statuses = set()
    for b, kind in enumerate(KINDS):
        log_b, cb_b = _record()
        alone = levenberg_marquardt(
            make_mixed([kind], DATA[b : b + 1]),
            X0[b : b + 1],
            opts,
            jacobian=jacobian,
            callback=cb_b,
        )
        torch.testing.assert_close(batch.x[b : b + 1], alone.x, rtol=1e-10, atol=0)
        torch.testing.assert_close(batch.cost[b : b + 1], alone.cost, rtol=1e-10, atol=0)
        for name in ("status", "n_iter", "nfev", "njev"):
            assert getattr(batch, name)[b] == getattr(alone, name)[0], (name, b)
        # Every iterate, not only the last: the batch log holds this problem's steps first.
        assert len(log_b) == int(alone.n_iter[0])
        for rec, rec_b in zip(log, log_b, strict=False):
            torch.testing.assert_close(rec.x[b : b + 1], rec_b.x, rtol=1e-10, atol=0)
            torch.testing.assert_close(rec.damping[b : b + 1], rec_b.damping, rtol=1e-10, atol=0)
            assert bool(rec.accepted[b]) == bool(rec_b.accepted[0])
        statuses.add(LMStatus(int(batch.status[b])))
    # The mix really is mixed: converged, iteration limit or failure all occur.
    assert statuses & {LMStatus.FTOL, LMStatus.XTOL, LMStatus.FTOL_XTOL, LMStatus.GTOL}
    assert batch.success[0] and batch.success[5]
    # Easy problems reach their minimiser x = c; the Rosenbrock ones x = (c0 + 1, 1).
    torch.testing.assert_close(batch.x[0], DATA[0], rtol=0, atol=1e-8)
    torch.testing.assert_close(
        batch.x[1], torch.tensor([1.5, 1.0], dtype=torch.float64), rtol=0, atol=1e-6
    )
    # Non-finite trials happened on the NaN problems and did not leak into the others.
    assert torch.isfinite(batch.x).all() and torch.isfinite(batch.cost).all()


def test_nan_trial_is_rejected_and_damping_raised():
    # r = sqrt(x) - 0.5: from x = 4 the Gauss-Newton step lands at x = -2 (NaN); from 0.3 not.
    opts = LMOptions(max_iter=50, initial_damping=1e-12)
    log, cb = _record()

    def residual(x):
        return torch.sqrt(x) - 0.5

    x0 = torch.tensor([[4.0], [0.3]], dtype=torch.float64)
    res = levenberg_marquardt(residual, x0, opts, callback=cb)
    assert res.success.all(), res.message
    torch.testing.assert_close(res.x, torch.full((2, 1), 0.25, dtype=torch.float64))
    first = log[0]
    assert first.accepted.tolist() == [False, True]  # the NaN trial was rejected ...
    torch.testing.assert_close(first.x[0], x0[0])  # ... and x restored
    assert first.damping[0] > opts.initial_damping  # damping raised
    assert first.damping[1] < opts.initial_damping  # the other problem went on as usual


def test_always_nonfinite_fails_after_max_bad_steps():
    def residual(x):
        # Problem 1 (odd rows, also in folded evaluations) is NaN everywhere but at its start.
        odd = (torch.arange(x.shape[0]) % 2 == 1)[:, None]
        poison = torch.where(odd & (x != 5.0), float("nan"), 0.0)
        return x - 1.0 + poison

    x0 = torch.tensor([[0.0, 0.0], [5.0, 5.0]], dtype=torch.float64)
    res = levenberg_marquardt(residual, x0, LMOptions(max_bad_steps=4), jacobian="forward")
    assert res.success[0] and res.statuses[1] == LMStatus.NONFINITE
    torch.testing.assert_close(res.x[0], torch.ones(2, dtype=torch.float64))
    assert int(res.n_iter[1]) == 4 and int(res.nfev[1]) == 5
    torch.testing.assert_close(res.x[1], x0[1])
    assert "not finite" in res.message[1]


def test_nonfinite_start_is_reported_not_raised():
    def residual(x):
        return torch.log(x) - 1.0

    x0 = torch.tensor([[1.0], [-1.0]], dtype=torch.float64)
    res = levenberg_marquardt(residual, x0)
    assert res.statuses[1] == LMStatus.NONFINITE and res.success[0]
    torch.testing.assert_close(res.x[0], torch.tensor([torch.e], dtype=torch.float64))
    assert int(res.n_iter[1]) == 0


def test_each_problem_stops_at_its_own_iteration_limit():
    """``max_iter`` per problem: a batch whose problems want different numbers of iterations
    gives each the solve it would have alone with its own limit."""
    opts = LMOptions(max_iter=60, ftol=1e-14, xtol=1e-14, gtol=1e-14, max_bad_steps=4)
    limits = torch.tensor([1, 3, 2, 5, 4, 1, 2])
    batch = levenberg_marquardt(make_mixed(KINDS, DATA), X0, opts, max_iter=limits)
    for b, kind in enumerate(KINDS):
        own = LMOptions(
            max_iter=int(limits[b]), ftol=1e-14, xtol=1e-14, gtol=1e-14, max_bad_steps=4
        )
        alone = levenberg_marquardt(make_mixed([kind], DATA[b : b + 1]), X0[b : b + 1], own)
        torch.testing.assert_close(batch.x[b : b + 1], alone.x, rtol=1e-10, atol=0)
        assert batch.n_iter[b] == alone.n_iter[0] <= limits[b]
        assert batch.status[b] == alone.status[0]
    assert (batch.status == LMStatus.MAX_ITER).sum() >= 3
    with pytest.raises(SolverError, match=r"max_iter: expected a \(7,\) tensor"):
        levenberg_marquardt(make_mixed(KINDS, DATA), X0, opts, max_iter=torch.tensor([1, 2]))
    with pytest.raises(SolverError, match="max_iter: expected integers >= 1"):
        levenberg_marquardt(make_mixed(KINDS, DATA), X0, opts, max_iter=torch.zeros(7))
