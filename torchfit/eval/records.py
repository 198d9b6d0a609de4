"""Runs and ground truth as records: what the accuracy report reads (design.md sections 5
and 8): ``truth.json`` per subject, and a run folder's ``summary.csv`` and per-subject
``measurements.json``. Lengths in metres; errors in % of the true value."""

from __future__ import annotations

import csv
import json
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

from torchfit.errors import DataError
from torchfit.io.dataset import validate_truth
from torchfit.measurements import MEASUREMENT_KEYS
from torchfit.status import SubjectStatus

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
FAILED = SubjectStatus.FAILED.value
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


def _fmt(value: float | None, spec: str) -> str:
    """``value`` formatted by ``spec``, or a dash for None (the report's table cells)."""
    return "—" if value is None else format(value, spec)
