"""The leave-one-out height regression of the benchmark report (the trivial predictor)."""

import numpy as np
import pytest

from torchfit.eval.baseline import height_regression_pct, loo_height_predictions
from torchfit.eval.records import ReportRow
from torchfit.eval.report import format_markdown, summarize


def _rows(n=9, seed=0, failed=()):
    rng = np.random.default_rng(seed)
    heights = rng.uniform(1.5, 1.95, n)
    rows = []
    for i, h in enumerate(heights):
        truth = {
            "height_m": float(h),
            "thigh_m": float(0.24 * h + rng.normal(0, 0.01)),
            "forearm_m": float(0.15 * h + rng.normal(0, 0.008)),
        }
        fitted = {k: v * (1 + rng.normal(0, 0.02)) for k, v in truth.items()}
        status = "failed" if i in failed else "ok"
        rows.append(ReportRow(f"s{i}", status, "", 1.0, truth, fitted))
    return rows


def test_loo_predictions_equal_a_direct_numpy_computation():
    rows = _rows(failed=(2,))
    used = [r for r in rows if not r.failed]
    h = np.array([r.truth["height_m"] for r in used])
    for key in ("thigh_m", "forearm_m"):
        y = np.array([r.truth[key] for r in used])
        direct = []
        for i in range(len(used)):
            others = np.arange(len(used)) != i
            slope, intercept = np.polyfit(h[others], y[others], 1)
            direct.append(intercept + slope * h[i])
        direct = np.array(direct)
        np.testing.assert_allclose(loo_height_predictions(h, y), direct, rtol=1e-10)
        expected = np.mean(np.abs(100 * (direct - y) / y))
        assert height_regression_pct(rows)[key] == pytest.approx(expected, rel=1e-10)
    # the height predicts itself; a measurement nobody has gives None
    assert height_regression_pct(rows)["height_m"] == pytest.approx(0.0, abs=1e-9)
    assert height_regression_pct(rows)["arm_span_m"] is None


def test_loo_needs_three_subjects():
    with pytest.raises(ValueError, match=">= 3 subjects"):
        loo_height_predictions([1.7, 1.8], [0.4, 0.42])


def test_report_marks_the_measurements_that_beat_it():
    rows = _rows()
    text = format_markdown(rows, summarize(rows))
    assert "height regression (LOO) %" in text
    line = next(t for t in text.splitlines() if t.startswith("| thigh |"))
    fit = summarize(rows).stats["thigh_m"].mean_abs_pct
    base = height_regression_pct(rows)["thigh_m"]
    assert line.split("|")[7].strip() == ("yes" if fit < base else "no")
