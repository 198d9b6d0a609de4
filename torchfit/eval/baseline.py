"""The trivial predictor a measurement must beat: a regression on the true height.

For every measurement, each subject's value is predicted by the straight line
``value = a + b * height`` fitted by least squares to the true values of the *other* subjects
of the report (leave-one-out), from the subject's own true height. Its mean absolute % error is
what anyone who knows the height and has measured a few other people gets without images. The
subjects are those the fit's means use (failed subjects left out), so the two compare one to
one.
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence

import numpy as np

from torchfit.eval.records import REPORT_KEYS, ReportRow

__all__ = ["loo_height_predictions", "height_regression_pct"]


def loo_height_predictions(heights: Sequence[float], values: Sequence[float]) -> np.ndarray:
    """(N,) leave-one-out predictions of ``values`` from ``heights`` by a straight line.

    Raises:
        ValueError: fewer than 3 subjects (a line through the others needs two).
    """
    h = np.asarray(heights, dtype=np.float64)
    y = np.asarray(values, dtype=np.float64)
    n = h.size
    if n < 3 or y.size != n:
        raise ValueError(f"need >= 3 subjects with height and value, got {n}")
    out = np.empty(n)
    for i in range(n):
        keep = np.arange(n) != i
        design = np.stack([np.ones(n - 1), h[keep]], 1)
        coef, *_ = np.linalg.lstsq(design, y[keep], rcond=None)
        out[i] = coef[0] + coef[1] * h[i]
    return out


def height_regression_pct(rows: Sequence[ReportRow]) -> Mapping[str, float | None]:
    """Measurement key -> mean absolute % error of the leave-one-out regression on the true
    height over the report's non-failed subjects (None with fewer than 3)."""
    out: dict[str, float | None] = {}
    for key in REPORT_KEYS:
        used = [
            r
            for r in rows
            if not r.failed and r.truth.get(key) is not None and r.truth.get("height_m")
        ]
        if len(used) < 3:
            out[key] = None
            continue
        truth = [r.truth[key] for r in used]
        pred = loo_height_predictions([r.truth["height_m"] for r in used], truth)
        out[key] = statistics.fmean(
            abs(100.0 * (p - t) / t) for p, t in zip(pred.tolist(), truth, strict=True)
        )
    return out
