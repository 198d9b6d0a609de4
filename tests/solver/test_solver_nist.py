"""The 27 NIST StRD nonlinear regression problems, solved against their certified values.

Problems of different ``P`` and ``M`` share one batch: parameters are padded (and held fixed by
``lower == upper == 0``) and residuals padded and masked (``benchmarks/nist_strd.py``). Accuracy
is the log relative error (LRE) of every parameter against NIST's certified value; a problem is
solved when its smallest LRE is >= 4 (the criterion of Ceres Solver's ``examples/nist.cc``). The
MINPACK column is ``scipy.optimize.leastsq`` (lmdif) on the same residuals, same tolerances.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from torchfit.solver import LMOptions, levenberg_marquardt, minpack_baseline

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import nist_strd  # noqa: E402

# One option set for every problem and both starts.
OPTIONS = LMOptions(max_iter=1000, ftol=1e-15, xtol=1e-15, gtol=0.0)
# Start 1 problems this solver does not solve with OPTIONS (see the report in the module):
# BoxBOD ends in a local minimum (RSS 9771.5, as MINPACK does); MGH10 drifts along the valley
# b1 -> 0 and hits max_iter.
KNOWN_START1_FAILURES = {"BoxBOD", "MGH10"}


def _solve(problems, starts, options=OPTIONS):
    fn, x0 = nist_strd.make_batch(problems, starts)
    lower = torch.full_like(x0, -torch.inf)
    upper = torch.full_like(x0, torch.inf)
    for b, prob in enumerate(problems):
        lower[b, prob.n_params :] = 0.0
        upper[b, prob.n_params :] = 0.0
    res = levenberg_marquardt(fn, x0, options, jacobian="autograd", lower=lower, upper=upper)
    lre = [
        float(nist_strd.log_relative_error(res.x[b, : p.n_params], p.certified).min())
        for b, p in enumerate(problems)
    ]
    return res, lre


def _minpack_lre(problems, starts):
    lre = []
    for prob, start in zip(problems, starts, strict=True):
        res = minpack_baseline(prob.residual, start[None], OPTIONS, max_nfev=20000)
        lre.append(float(nist_strd.log_relative_error(res.x[0], prob.certified).min()))
    return lre


def _table(problems, rows):
    lines = [f"{'problem':10s} " + " ".join(f"{h:>9s}" for h in rows)]
    for i, prob in enumerate(problems):
        lines.append(f"{prob.name:10s} " + " ".join(f"{rows[h][i]:9.1f}" for h in rows))
    return "\n".join(lines)


def test_models_reproduce_the_certified_rss(shared_data):
    """The hand-coded models give NIST's certified RSS at the certified parameters."""
    for prob in nist_strd.load_all(shared_data / "nist-strd"):
        rss = float((prob.residual(prob.certified[None]) ** 2).sum())
        if prob.name == "Lanczos1":  # certified RSS 1.4e-25: exact fit up to rounding
            assert rss < 1e-19
        else:
            assert rss == pytest.approx(prob.certified_rss, rel=1e-9), prob.name


def test_nist_start2_all_27_in_one_batch(shared_data):
    """Start 2 (near the optimum): every parameter of all 27 problems to LRE >= 4."""
    problems = nist_strd.load_all(shared_data / "nist-strd")
    res, lre = _solve(problems, [p.start2 for p in problems])
    print("\n" + _table(problems, {"LRE s2": lre}))
    failed = [p.name for p, v in zip(problems, lre, strict=True) if v < 4]
    assert failed == []
    assert res.success.all()


@pytest.mark.slow
def test_nist_both_starts_one_batch_against_minpack(shared_data):
    """All 27 problems from both starts in one batch of 54, against MINPACK from the same starts."""
    problems = nist_strd.load_all(shared_data / "nist-strd")
    starts = [p.start1 for p in problems] + [p.start2 for p in problems]
    _, lre = _solve(problems + problems, starts)
    n = len(problems)
    ours1, ours2 = lre[:n], lre[n:]
    mp1 = _minpack_lre(problems, starts[:n])
    mp2 = _minpack_lre(problems, starts[n:])
    rows = {"ours s1": ours1, "MINPACK s1": mp1, "ours s2": ours2, "MINPACK s2": mp2}
    print("\n" + _table(problems, rows))
    solved = {k: sum(v >= 4 for v in col) for k, col in rows.items()}
    print("solved (LRE >= 4):", solved)
    assert solved["ours s2"] == n
    failed1 = {p.name for p, v in zip(problems, ours1, strict=True) if v < 4}
    assert failed1 <= KNOWN_START1_FAILURES
    # The bar (Start 1: at least MINPACK's count) is checked, and for now missed, by
    # test_nist_start1_at_least_minpack.


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="MGH10 from Start 1 is not solved (max_iter reached)")
def test_nist_start1_at_least_minpack(shared_data):
    problems = nist_strd.load_all(shared_data / "nist-strd")
    starts = [p.start1 for p in problems]
    _, ours = _solve(problems, starts)
    mp = _minpack_lre(problems, starts)
    assert sum(v >= 4 for v in ours) >= sum(v >= 4 for v in mp)
