"""Accuracy report of a run against ground truth (design.md section 9, the first paper's Table 1).

Pure functions from files to tables: read ``truth.json`` and a run folder (``summary.csv`` and
per-subject ``measurements.json``, design.md section 8), pair them per subject, compute the
per-subject error ``100 (fitted - true) / true`` in % and the mean absolute % error per
measurement, and write the report as markdown, CSV and a PNG of fitted against true values.

Lengths are metres (design.md section 5). Failed subjects are listed but excluded from the
means; a subject without ground truth is skipped with a note. The run's method is taken from
the subjects' statuses: ``template`` means the template's measurements at the nominal postures
(no fit), the baseline a fit must beat; any other non-failed status is a fit result.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import statistics
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from torchfit.errors import DataError
from torchfit.io.dataset import validate_truth
from torchfit.measurements import MEASUREMENT_KEYS

__all__ = [
    "REPORT_KEYS",
    "LABELS",
    "PAPER_TABLE1_PCT",
    "FAILED",
    "TEMPLATE",
    "ResultLike",
    "SubjectOutcome",
    "ReportRow",
    "MeasurementStats",
    "ReportSummary",
    "read_truth",
    "collect_truths",
    "read_run",
    "build_rows",
    "summarize",
    "describe_method",
    "format_markdown",
    "write_csv",
    "write_summary_csv",
    "plot_fitted_vs_true",
    "write_report",
]

log = logging.getLogger(__name__)

#: Measurements of the report, in order (the first paper's Table 1 and the segment lengths).
REPORT_KEYS: tuple[str, ...] = MEASUREMENT_KEYS[: MEASUREMENT_KEYS.index("shoulder_width_m") + 1]
#: Human-readable names of :data:`REPORT_KEYS`.
LABELS: dict[str, str] = {
    "height_m": "height",
    "arm_span_m": "arm span",
    "lower_leg_m": "lower leg",
    "thigh_m": "thigh",
    "upper_arm_m": "upper arm",
    "forearm_m": "forearm",
    "shoulder_width_m": "shoulder width",
}
#: Mean absolute % errors of the first paper's Table 1, for comparison.
PAPER_TABLE1_PCT: dict[str, float] = {"height_m": 2.1, "arm_span_m": 1.6, "lower_leg_m": 7.6}
#: Status of a subject that could not be processed (``torchfit.pipeline``).
FAILED = "failed"
#: Status of the template's measurements without a fit (``torchfit.pipeline``).
TEMPLATE = "template"


class ResultLike(Protocol):
    """What the report needs of one subject's result (``torchfit.pipeline.SubjectResult``)."""

    name: str
    status: str
    message: str
    measurements: dict[str, float]
    seconds: float


@dataclass
class SubjectOutcome:
    """One subject's result read back from a run folder (a :class:`ResultLike`)."""

    name: str
    status: str
    message: str = ""
    measurements: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0


@dataclass(frozen=True)
class ReportRow:
    """One subject of the report: true and fitted values (metres), status and time.

    ``seconds`` is None where the run did not time the subject (e.g. resumed from disk).
    """

    subject: str
    status: str
    message: str
    seconds: float | None
    truth: Mapping[str, float]
    fitted: Mapping[str, float]

    @property
    def failed(self) -> bool:
        """True for a failed subject (excluded from the means)."""
        return self.status == FAILED

    def error_pct(self, key: str) -> float | None:
        """Signed error ``100 (fitted - true) / true`` of ``key`` in %, None if unknown."""
        true, fit = self.truth.get(key), self.fitted.get(key)
        if self.failed or true is None or fit is None:
            return None
        return 100.0 * (fit - true) / true


@dataclass(frozen=True)
class MeasurementStats:
    """Errors of one measurement over the subjects that have it (failed ones excluded)."""

    key: str
    n: int
    mean_abs_pct: float | None
    mean_signed_pct: float | None
    max_abs_pct: float | None


@dataclass(frozen=True)
class ReportSummary:
    """What the report says about the whole run."""

    method: str
    statuses: dict[str, int]
    n_subjects: int
    n_failed: int
    stats: dict[str, MeasurementStats]
    mean_seconds: float | None
    median_seconds: float | None
    n_timed: int


# ------------------------------------------------------------------------------------------
# Reading


def _read_json(path: Path, what: str) -> object:
    if not path.is_file():
        raise DataError(f"{path}: {what} not found")
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: cannot read {what}: {exc}") from exc


def read_truth(path: str | Path) -> dict[str, float]:
    """The measurements of one ``truth.json`` (metres; ``joints_world`` is left out).

    Raises:
        DataError: the file is missing, not JSON, or not a valid truth file (message names it).
    """
    path = Path(path)
    data = _read_json(path, "truth.json")
    problems = validate_truth(data, str(path))
    if problems:
        raise DataError("; ".join(problems))
    return {k: float(v) for k, v in dict(data).items() if k != "joints_world"}


def collect_truths(
    folders: Mapping[str, str | Path],
) -> tuple[dict[str, dict[str, float]], list[str]]:
    """Ground truth of every subject folder that has a valid ``truth.json``.

    Args:
        folders: subject name -> subject folder.

    Returns:
        ``(truths, notes)``: name -> measurements for the subjects with ground truth, and one
        note per skipped subject (no ``truth.json``, or an invalid one) saying why.
    """
    truths: dict[str, dict[str, float]] = {}
    notes: list[str] = []
    for name, folder in folders.items():
        path = Path(folder) / "truth.json"
        if not path.is_file():
            notes.append(f"{name}: skipped, no truth.json in {folder}")
            continue
        try:
            truths[name] = read_truth(path)
        except DataError as exc:
            notes.append(f"{name}: skipped, {exc}")
    return truths, notes


def _float_or_none(text: str | None) -> float | None:
    if text is None or text.strip() == "":
        return None
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def read_run(run_dir: str | Path) -> list[SubjectOutcome]:
    """Read a run folder: statuses and times from ``summary.csv``, values from
    ``<subject>/measurements.json``.

    A subject whose status is not failed but whose ``measurements.json`` is missing or
    unreadable comes back failed, with a message naming the file.

    Raises:
        DataError: ``run_dir`` or its ``summary.csv`` is missing, unreadable, lacks the
            ``subject`` / ``status`` columns or has no rows.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise DataError(f"run folder not found: {run_dir}")
    path = run_dir / "summary.csv"
    if not path.is_file():
        raise DataError(f"{path}: summary.csv not found (is {run_dir} a torchfit run folder?)")
    try:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            columns = reader.fieldnames or []
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DataError(f"{path}: cannot read summary.csv: {exc}") from exc
    missing = [c for c in ("subject", "status") if c not in columns]
    if missing:
        raise DataError(f"{path}: missing columns {missing} (found {columns})")
    if not rows:
        raise DataError(f"{path}: no subjects in summary.csv")
    outcomes = []
    for row in rows:
        name, status = row["subject"], row["status"]
        seconds = _float_or_none(row.get("seconds")) or 0.0
        outcome = SubjectOutcome(name, status, row.get("message") or "", {}, seconds)
        if status != FAILED:
            try:
                data = _read_json(run_dir / name / "measurements.json", "measurements.json")
                if not isinstance(data, dict):
                    raise DataError(f"{run_dir / name / 'measurements.json'}: not a JSON object")
            except DataError as exc:
                log.warning("%s", exc)
                outcome.status, outcome.message = FAILED, str(exc)
            else:
                outcome.measurements = {
                    k: float(v)
                    for k, v in data.items()
                    if k in REPORT_KEYS
                    and isinstance(v, (int, float))
                    and not isinstance(v, bool)
                    and math.isfinite(v)
                }
        outcomes.append(outcome)
    return outcomes


# ------------------------------------------------------------------------------------------
# Tables


def build_rows(
    results: Iterable[ResultLike], truths: Mapping[str, Mapping[str, float]]
) -> tuple[list[ReportRow], list[str]]:
    """Pair each result with its ground truth.

    Args:
        results: one result per subject (``SubjectResult`` or :class:`SubjectOutcome`).
        truths: subject name -> true measurements (metres).

    Returns:
        ``(rows, notes)``: one row per result that has ground truth, in the order of
        ``results``, and one note per result skipped for want of ground truth.
    """
    rows, notes = [], []
    for r in results:
        if r.name not in truths:
            notes.append(f"{r.name}: skipped, no ground truth")
            continue
        fitted = {k: float(v) for k, v in r.measurements.items() if v is not None}
        seconds = float(r.seconds) if r.seconds and r.seconds > 0 else None
        rows.append(ReportRow(r.name, r.status, r.message, seconds, dict(truths[r.name]), fitted))
    return rows, notes


def describe_method(statuses: Mapping[str, int]) -> str:
    """``"template (no fit)"``, ``"fit"``, ``"mixed: …"`` or ``"none (all failed)"``."""
    used = {s: n for s, n in statuses.items() if s != FAILED and n > 0}
    if not used:
        return "none (all failed)"
    if set(used) == {TEMPLATE}:
        return "template (no fit)"
    if TEMPLATE not in used:
        return "fit"
    n_fit = sum(n for s, n in used.items() if s != TEMPLATE)
    return f"mixed: {n_fit} fit, {used[TEMPLATE]} template (no fit)"


def summarize(rows: Sequence[ReportRow]) -> ReportSummary:
    """Mean absolute, mean signed and largest absolute % error per measurement, times, method."""
    statuses = dict(Counter(r.status for r in rows))
    stats = {}
    for key in REPORT_KEYS:
        errors = [e for r in rows if (e := r.error_pct(key)) is not None]
        stats[key] = MeasurementStats(
            key,
            len(errors),
            statistics.fmean(abs(e) for e in errors) if errors else None,
            statistics.fmean(errors) if errors else None,
            max(abs(e) for e in errors) if errors else None,
        )
    times = [r.seconds for r in rows if not r.failed and r.seconds is not None]
    return ReportSummary(
        method=describe_method(statuses),
        statuses=statuses,
        n_subjects=len(rows),
        n_failed=sum(r.failed for r in rows),
        stats=stats,
        mean_seconds=statistics.fmean(times) if times else None,
        median_seconds=statistics.median(times) if times else None,
        n_timed=len(times),
    )


def _fmt(value: float | None, spec: str) -> str:
    return "—" if value is None else format(value, spec)


def format_markdown(
    rows: Sequence[ReportRow],
    summary: ReportSummary,
    *,
    data: str | Path | None = None,
    run_dir: str | Path | None = None,
    notes: Sequence[str] = (),
    plot: str | None = None,
    settings: Mapping[str, str] | None = None,
) -> str:
    """The report as markdown: method, summary table (with the paper's figures), per subject.

    Args:
        rows, summary: from :func:`build_rows` and :func:`summarize`.
        data, run_dir: the dataset and the run folder, stated in the header.
        notes: skipped subjects and other remarks, listed at the end.
        plot: file name of the fitted-against-true PNG, linked when given.
        settings: further header lines, e.g. ``{"config": "configs/demo.yaml"}``.
    """
    s = summary
    statuses = ", ".join(f"{n} `{st}`" for st, n in sorted(s.statuses.items()))
    out = [f"# Accuracy benchmark: {s.method}", ""]
    if s.method.startswith(TEMPLATE):
        out += [
            "> **Baseline, not a fit result.** Every subject has status `template`: the values "
            "are the template's own measurements (no fit). A fit must beat these errors.",
            "",
        ]
    elif s.method.startswith("mixed"):
        out += [
            "> **Mixed run.** Some subjects were fitted and some report the template (no fit); "
            "the means below mix both. See the status column.",
            "",
        ]
    out += [f"- Method: **{s.method}** (statuses: {statuses or 'none'})"]
    if data is not None:
        out.append(f"- Data: `{data}`")
    if run_dir is not None:
        out.append(f"- Run folder: `{run_dir}`")
    out += [f"- {name}: `{value}`" for name, value in (settings or {}).items()]
    out.append(
        f"- Subjects with ground truth: {s.n_subjects}; failed: {s.n_failed} (excluded from the "
        f"means); skipped: {len(notes)}"
    )
    if s.n_timed:
        out.append(
            f"- Seconds per subject: mean {s.mean_seconds:.2f}, median {s.median_seconds:.2f} "
            f"(over {s.n_timed} timed subjects)"
        )
    else:
        out.append("- Seconds per subject: not measured (no timed subject)")
    out += [
        "- Error = 100 (fitted − true) / true, in %; measurement definitions: design.md section 5.",
        "",
        "## Mean absolute error per measurement",
        "",
        "| measurement | n | mean abs. error % | mean signed error % | max abs. error % "
        "| paper Table 1 % |",
        "|---|--:|--:|--:|--:|--:|",
    ]
    for key in REPORT_KEYS:
        st = s.stats[key]
        out.append(
            f"| {LABELS[key]} | {st.n} | {_fmt(st.mean_abs_pct, '.1f')} | "
            f"{_fmt(st.mean_signed_pct, '+.1f')} | {_fmt(st.max_abs_pct, '.1f')} | "
            f"{_fmt(PAPER_TABLE1_PCT.get(key), '.1f')} |"
        )
    out += ["", "Paper: first paper, Table 1 (mean error)."]
    if plot:
        out += ["", f"![fitted against true]({plot})"]
    out += [
        "",
        "## Per subject",
        "",
        "Each cell: true / fitted in metres (error %).",
        "",
        "| subject | status | s | " + " | ".join(LABELS[k] for k in REPORT_KEYS) + " |",
        "|---|---|--:|" + "--:|" * len(REPORT_KEYS),
    ]
    for r in rows:
        cells = []
        for key in REPORT_KEYS:
            true, fit, err = r.truth.get(key), r.fitted.get(key), r.error_pct(key)
            cells.append(f"{_fmt(true, '.3f')} / {_fmt(fit, '.3f')} ({_fmt(err, '+.1f')})")
        out.append(f"| {r.subject} | {r.status} | {_fmt(r.seconds, '.1f')} | {' | '.join(cells)} |")
    failed = [r for r in rows if r.failed]
    if failed:
        out += ["", f"## Failed subjects ({len(failed)}, excluded from the means)", ""]
        out += [f"- {r.subject}: {r.message or 'no message'}" for r in failed]
    if notes:
        out += ["", f"## Skipped ({len(notes)})", ""]
        out += [f"- {n}" for n in notes]
    return "\n".join(out) + "\n"


def write_csv(rows: Sequence[ReportRow], path: str | Path) -> None:
    """One row per subject: status, seconds, then true, fitted and error % per measurement."""
    columns = ["subject", "status", "seconds"]
    for key in REPORT_KEYS:
        columns += [f"{key}_true", f"{key}_fitted", f"{key.removesuffix('_m')}_error_pct"]
    columns.append("message")

    def num(v: float | None, digits: int) -> str:
        return "" if v is None else f"{v:.{digits}f}"

    with Path(path).open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(columns)
        for r in rows:
            line = [r.subject, r.status, num(r.seconds, 3)]
            for key in REPORT_KEYS:
                line += [
                    num(r.truth.get(key), 5),
                    num(r.fitted.get(key), 5),
                    num(r.error_pct(key), 3),
                ]
            writer.writerow([*line, r.message])


def write_summary_csv(summary: ReportSummary, path: str | Path) -> None:
    """One row per measurement: n, mean absolute / mean signed / max absolute % error, paper."""

    def num(v: float | None) -> str:
        return "" if v is None else f"{v:.3f}"

    with Path(path).open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            ["measurement", "method", "n", "mean_abs_error_pct", "mean_signed_error_pct"]
            + ["max_abs_error_pct", "paper_table1_pct"]
        )
        for key in REPORT_KEYS:
            st = summary.stats[key]
            writer.writerow(
                [key, summary.method, st.n, num(st.mean_abs_pct), num(st.mean_signed_pct)]
                + [num(st.max_abs_pct), num(PAPER_TABLE1_PCT.get(key))]
            )


# ------------------------------------------------------------------------------------------
# Plot (OpenCV drawing; BGR colours)

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


def write_report(
    out_dir: str | Path,
    rows: Sequence[ReportRow],
    *,
    data: str | Path | None = None,
    run_dir: str | Path | None = None,
    notes: Sequence[str] = (),
    settings: Mapping[str, str] | None = None,
) -> dict[str, Path]:
    """Write ``report.md``, ``report.csv``, ``report_summary.csv`` and ``report.png``.

    ``data``, ``run_dir``, ``notes`` and ``settings`` go to the markdown header
    (:func:`format_markdown`).

    Returns:
        file kind (``"markdown"``, ``"csv"``, ``"summary_csv"``, ``"plot"``) -> path written.

    Raises:
        DataError: ``rows`` is empty (nothing to report).
    """
    if not rows:
        raise DataError("rows: no subject with ground truth to report")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(rows)
    paths = {
        "markdown": out / "report.md",
        "csv": out / "report.csv",
        "summary_csv": out / "report_summary.csv",
        "plot": out / "report.png",
    }
    plot_fitted_vs_true(rows, summary, paths["plot"])
    paths["markdown"].write_text(
        format_markdown(
            rows,
            summary,
            data=data,
            run_dir=run_dir,
            notes=notes,
            plot=paths["plot"].name,
            settings=settings,
        )
    )
    write_csv(rows, paths["csv"])
    write_summary_csv(summary, paths["summary_csv"])
    return paths
