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
import logging
import statistics
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

from torchfit.errors import DataError
from torchfit.eval.baseline import height_regression_pct
from torchfit.eval.plot import plot_fitted_vs_true
from torchfit.eval.records import (
    FAILED,
    LABELS,
    PAPER_TABLE1_PCT,
    REPORT_KEYS,
    TEMPLATE,
    MeasurementStats,
    ReportRow,
    ReportSummary,
    ResultLike,
    SubjectOutcome,
    _fmt,
    collect_truths,
    read_run,
    read_truth,
)

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
    "write_report",
]

log = logging.getLogger(__name__)


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
        "| height regression (LOO) % | beats it | paper Table 1 % |",
        "|---|--:|--:|--:|--:|--:|:-:|--:|",
    ]
    regression = height_regression_pct(rows)
    for key in REPORT_KEYS:
        st = s.stats[key]
        out.append(
            f"| {LABELS[key]} | {st.n} | {_fmt(st.mean_abs_pct, '.1f')} | "
            f"{_fmt(st.mean_signed_pct, '+.1f')} | {_fmt(st.max_abs_pct, '.1f')} | "
            f"{_fmt(regression[key], '.1f')} | {_beats(st.mean_abs_pct, regression[key])} | "
            f"{_fmt(PAPER_TABLE1_PCT.get(key), '.1f')} |"
        )
    out += [
        "",
        "Height regression (LOO): each subject's measurement predicted from its true height by "
        "a straight line fitted to the other subjects' truth (the trivial predictor; height "
        "itself is then exact). Beats it: the fit's mean absolute error is lower.",
        "Paper: first paper, Table 1 (mean error).",
    ]
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


def _beats(fit: float | None, baseline: float | None) -> str:
    if fit is None or baseline is None:
        return "—"
    return "yes" if fit < baseline else "no"


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


def write_summary_csv(
    summary: ReportSummary, path: str | Path, regression: Mapping[str, float | None] | None = None
) -> None:
    """One row per measurement: n, mean absolute / mean signed / max absolute % error, the
    leave-one-out height regression's mean absolute % error (:mod:`torchfit.eval.baseline`)
    and whether the fit beats it, the paper."""
    regression = regression or {}

    def num(v: float | None) -> str:
        return "" if v is None else f"{v:.3f}"

    with Path(path).open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            ["measurement", "method", "n", "mean_abs_error_pct", "mean_signed_error_pct"]
            + ["max_abs_error_pct", "height_regression_loo_pct", "beats_regression"]
            + ["paper_table1_pct"]
        )
        for key in REPORT_KEYS:
            st = summary.stats[key]
            base = regression.get(key)
            writer.writerow(
                [key, summary.method, st.n, num(st.mean_abs_pct), num(st.mean_signed_pct)]
                + [num(st.max_abs_pct), num(base), _beats(st.mean_abs_pct, base)]
                + [num(PAPER_TABLE1_PCT.get(key))]
            )


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
    write_summary_csv(summary, paths["summary_csv"], height_regression_pct(rows))
    return paths
