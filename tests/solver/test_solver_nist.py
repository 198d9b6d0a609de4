"""The 27 NIST StRD nonlinear regression problems, solved against their certified values.

Problems of different ``P`` and ``M`` share one batch: parameters are padded (and held fixed by
``lower == upper == 0``) and residuals padded and masked (``benchmarks/nist_strd.py``). Accuracy
is the log relative error (LRE) of every parameter against NIST's certified value; a problem is
solved when its smallest LRE is >= 4 (the criterion of Ceres Solver's ``examples/nist.cc``). The
MINPACK column is ``scipy.optimize.leastsq`` (lmdif) on the same residuals, same tolerances.

Both solvers get the same budget: ``OPTIONS.max_nfev`` = 20000 residual evaluations per problem,
counted as lmdif counts them (every evaluation, plus one per free parameter for each Jacobian,
which is what lmdif's forward differences cost; for the LM solver that includes the extra
evaluation per trial step of the geodesic acceleration). ``max_iter`` is set as high, so that
the evaluation budget is the limit for both.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from torchfit.solver import LMOptions, levenberg_marquardt, minpack_baseline

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import nist_strd  # noqa: E402

# One option set for every problem and both starts; the same evaluation budget for MINPACK.
BUDGET = 20000
OPTIONS = LMOptions(
    max_iter=BUDGET,
    max_nfev=BUDGET,
    ftol=1e-15,
    xtol=1e-15,
    gtol=0.0,
    geodesic_acceleration=True,
)
# Start 1 problems this solver does not solve with OPTIONS: none. (Without the geodesic
# acceleration it missed BoxBOD, which stops on the plateau b2 -> inf with RSS 9771.5 as MINPACK
# does, and MGH10, which ran to b1 ~ 1e-50 along its valley and needed ~25000 evaluations.)
KNOWN_START1_FAILURES: set[str] = set()


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


def _evaluations(res, problems):
    """Evaluations each problem spent, counted as ``max_nfev`` counts them."""
    return [int(res.nfev[b]) + p.n_params * int(res.njev[b]) for b, p in enumerate(problems)]


def _minpack(problems, starts):
    """LRE and evaluations of lmdif, one problem at a time, with OPTIONS' budget."""
    lre, nfev = [], []
    for prob, start in zip(problems, starts, strict=True):
        res = minpack_baseline(prob.residual, start[None], OPTIONS)
        lre.append(float(nist_strd.log_relative_error(res.x[0], prob.certified).min()))
        nfev.append(int(res.nfev[0]))
    return lre, nfev


def _table(problems, rows):
    lines = [f"{'problem':10s} " + " ".join(f"{h:>10s}" for h in rows)]
    for i, prob in enumerate(problems):
        cells = (
            f"{v:10d}" if isinstance(v, int) else f"{v:10.1f}" for v in (rows[h][i] for h in rows)
        )
        lines.append(f"{prob.name:10s} " + " ".join(cells))
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
    """All 27 problems from both starts in one batch of 54, against MINPACK from the same
    starts with the same evaluation budget: Start 2 all 27, Start 1 at least MINPACK's count."""
    problems = nist_strd.load_all(shared_data / "nist-strd")
    starts = [p.start1 for p in problems] + [p.start2 for p in problems]
    res, lre = _solve(problems + problems, starts)
    evals = _evaluations(res, problems + problems)
    n = len(problems)
    ours1, ours2 = lre[:n], lre[n:]
    mp1, mp_ev1 = _minpack(problems, starts[:n])
    mp2, mp_ev2 = _minpack(problems, starts[n:])
    rows = {"ours s1": ours1, "MINPACK s1": mp1, "ours s2": ours2, "MINPACK s2": mp2}
    nfev = {
        "ev ours s1": evals[:n],
        "ev MP s1": mp_ev1,
        "ev ours s2": evals[n:],
        "ev MP s2": mp_ev2,
    }
    print("\n" + _table(problems, rows | nfev))
    solved = {k: sum(v >= 4 for v in col) for k, col in rows.items()}
    print(f"solved (LRE >= 4, budget {BUDGET} evaluations each):", solved)
    # The budget is checked after each iteration, which spends at most P + 2 evaluations.
    assert max(evals) < BUDGET + max(p.n_params for p in problems) + 2
    assert solved["ours s2"] == n
    failed1 = {p.name for p, v in zip(problems, ours1, strict=True) if v < 4}
    assert failed1 == KNOWN_START1_FAILURES
    assert solved["ours s1"] >= solved["MINPACK s1"]  # the bar
