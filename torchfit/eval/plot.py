"""The report's plot: fitted against true value per measurement (OpenCV drawing, BGR)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from torchfit.errors import DataError
from torchfit.eval.records import (
    LABELS,
    REPORT_KEYS,
    TEMPLATE,
    MeasurementStats,
    ReportRow,
    ReportSummary,
    _fmt,
)

__all__ = ["plot_fitted_vs_true"]


_INK, _GRID, _IDENTITY, _POINT = (40, 40, 40), (225, 225, 225), (120, 120, 120), (200, 90, 20)
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _nice_ticks(lo: float, hi: float, target: int = 6) -> list[float]:
    raw = (hi - lo) / max(target, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    return [first + i * step for i in range(int((hi - first) / step + 1e-9) + 1)]


def _text(
    img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.45, thick: int = 1
) -> None:
    cv2.putText(img, text, org, _FONT, scale, _INK, thick, cv2.LINE_AA)


def _text_centered(img: np.ndarray, text: str, cx: int, y: int, scale: float = 0.45) -> None:
    (w, _), _ = cv2.getTextSize(text, _FONT, scale, 1)
    _text(img, text, (cx - w // 2, y), scale)


def _panel(key: str, rows: Sequence[ReportRow], stats: MeasurementStats, size: int) -> np.ndarray:
    img = np.full((size, size, 3), 255, np.uint8)
    left, right, top, bottom = 70, 18, 44, 56
    x0, x1, y0, y1 = left, size - right, top, size - bottom
    title = f"{LABELS[key]}: mean abs. error {_fmt(stats.mean_abs_pct, '.1f')} % (n={stats.n})"
    _text_centered(img, title, size // 2, 24, 0.5)
    pairs = [
        (r.truth[key], r.fitted[key])
        for r in rows
        if not r.failed and key in r.truth and key in r.fitted
    ]
    cv2.rectangle(img, (x0, y0), (x1, y1), _INK, 1)
    if not pairs:
        _text_centered(img, "no data", (x0 + x1) // 2, (y0 + y1) // 2)
        return img
    values = [v for p in pairs for v in p]
    lo, hi = min(values), max(values)
    pad = max(0.06 * (hi - lo), 0.01 * max(abs(hi), 1e-3))
    lo, hi = lo - pad, hi + pad

    def px(v: float) -> int:
        return int(round(x0 + (v - lo) / (hi - lo) * (x1 - x0)))

    def py(v: float) -> int:
        return int(round(y1 - (v - lo) / (hi - lo) * (y1 - y0)))

    ticks = _nice_ticks(lo, hi)
    step = ticks[1] - ticks[0] if len(ticks) > 1 else hi - lo
    decimals = min(max(math.ceil(-math.log10(step) - 1e-9), 1), 3)
    for t in ticks:
        label = f"{t:.{decimals}f}"
        cv2.line(img, (px(t), y0 + 1), (px(t), y1 - 1), _GRID, 1)
        cv2.line(img, (x0 + 1, py(t)), (x1 - 1, py(t)), _GRID, 1)
        cv2.line(img, (px(t), y1), (px(t), y1 + 5), _INK, 1)
        cv2.line(img, (x0 - 5, py(t)), (x0, py(t)), _INK, 1)
        _text_centered(img, label, px(t), y1 + 20, 0.4)
        (w, h), _ = cv2.getTextSize(label, _FONT, 0.4, 1)
        _text(img, label, (x0 - 8 - w, py(t) + h // 2), 0.4)
    cv2.rectangle(img, (x0, y0), (x1, y1), _INK, 1)
    cv2.line(img, (px(lo), py(lo)), (px(hi), py(hi)), _IDENTITY, 1, cv2.LINE_AA)
    for true, fit in pairs:
        cv2.circle(img, (px(true), py(fit)), 5, _POINT, -1, cv2.LINE_AA)
        cv2.circle(img, (px(true), py(fit)), 5, _INK, 1, cv2.LINE_AA)
    _text_centered(img, "true (m)", (x0 + x1) // 2, size - 12, 0.45)
    label = np.full((22, y1 - y0, 3), 255, np.uint8)
    _text_centered(label, "fitted (m)", label.shape[1] // 2, 16, 0.45)
    img[y0:y1, 4:26] = cv2.rotate(label, cv2.ROTATE_90_COUNTERCLOCKWISE)
    return img


def plot_fitted_vs_true(
    rows: Sequence[ReportRow], summary: ReportSummary, path: str | Path, panel_size: int = 420
) -> np.ndarray:
    """Write a PNG of fitted against true values, one panel per measurement.

    Each panel has ticks in metres, the identity line (grey) and one dot per non-failed
    subject; the last panel states the method and the subject counts.

    Returns:
        (H, W, 3) uint8 BGR image, as written.

    Raises:
        DataError: the PNG cannot be written.
    """
    panels = [_panel(k, rows, summary.stats[k], panel_size) for k in REPORT_KEYS]
    legend = np.full((panel_size, panel_size, 3), 255, np.uint8)
    lines = [
        "fitted against true",
        f"method: {summary.method}",
        f"subjects: {summary.n_subjects - summary.n_failed} shown, {summary.n_failed} failed",
        "grey line: fitted = true",
    ]
    if summary.method.startswith(TEMPLATE):
        lines.append("BASELINE: template measurements, no fit")
    for i, line in enumerate(lines):
        _text(legend, line, (20, 60 + 30 * i), 0.5, thick=2 if i == 0 else 1)
    cv2.circle(legend, (30, 60 + 30 * len(lines) + 10), 5, _POINT, -1, cv2.LINE_AA)
    _text(legend, "one subject", (45, 60 + 30 * len(lines) + 15), 0.5)
    panels.append(legend)
    while len(panels) % 4:
        panels.append(np.full_like(legend, 255))
    grid = np.vstack([np.hstack(panels[i : i + 4]) for i in range(0, len(panels), 4)])
    if not cv2.imwrite(str(path), grid):
        raise DataError(f"{path}: cannot write the PNG")
    return grid
