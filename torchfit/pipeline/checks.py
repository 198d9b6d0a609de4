"""What the judge checks a fitted body against, without the truth: human proportions (from
ANSUR II) and scales that ended on their upper bound.

The proportion table ``proportions.csv`` beside this module is derived by
``tools/make_proportions.py``: per measurement, the 0.5th and 99.5th percentiles of its ratio
to the height among the 6068 soldiers of ANSUR II. ANSUR II measures skin landmarks, the model
joint centres (a joint-centre upper arm is about 15 % shorter than acromion to radiale, a
joint-centre lower leg about 8 % longer than the tibial height), so a fit is implausible only
outside the range widened by :data:`MARGINS`; arm span, fingertip to fingertip in both, gets a
narrow margin.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from functools import lru_cache
from pathlib import Path

__all__ = ["PROPORTIONS_CSV", "MARGINS", "load_proportions", "proportion_flags", "bound_flags"]

#: The committed table (``tools/make_proportions.py``).
PROPORTIONS_CSV = Path(__file__).with_name("proportions.csv")

#: Relative widening of each ANSUR II range on both sides (definitions differ; see above).
MARGINS: dict[str, float] = {
    "arm_span_m": 0.03,
    "upper_arm_m": 0.25,
    "forearm_m": 0.2,
    "lower_leg_m": 0.2,
    "thigh_m": 0.2,
    "shoulder_width_m": 0.25,
}


@lru_cache(maxsize=4)
def load_proportions(path: Path = PROPORTIONS_CSV) -> dict[str, tuple[float, float]]:
    """measurement key -> (0.5th, 99.5th percentile) of its ratio to the height."""
    with Path(path).open(newline="") as f:
        return {r["measurement"]: (float(r["p0_5"]), float(r["p99_5"])) for r in csv.DictReader(f)}


def proportion_flags(
    measurements: Mapping[str, float],
    table: Mapping[str, tuple[float, float]] | None = None,
    margins: Mapping[str, float] = MARGINS,
) -> list[str]:
    """Messages for the measurements whose ratio to ``height_m`` is far from human.

    Args:
        measurements: measurement key -> metres (``height_m`` among them).
        table: key -> (low, high) ratio range (default: :func:`load_proportions`).
        margins: key -> relative widening of the range on both sides.

    Returns:
        One message per implausible ratio, e.g. ``"arm_span / height 1.60 outside 0.88-1.20
        (ANSUR II, widened)"``.
    """
    table = load_proportions() if table is None else table
    height = measurements.get("height_m")
    if not height or height <= 0:
        return []
    flags = []
    for key, (lo, hi) in table.items():
        if key not in measurements:
            continue
        m = margins.get(key, 0.0)
        low, high = lo * (1 - m), hi * (1 + m)
        ratio = measurements[key] / height
        if not low <= ratio <= high:
            flags.append(
                f"{key[:-2]} / height {ratio:.3f} outside {low:.3f}-{high:.3f} (ANSUR II, widened)"
            )
    return flags


def bound_flags(
    scales: Sequence[float], names: Sequence[str], bounds: tuple[float, float], tol: float = 0.01
) -> list[str]:
    """Messages for the scale groups within ``tol`` (relative) of the upper bound of ``bounds``.

    Only the upper bound: a segment stretched to the limit is what a drag does, while the
    lower bound is reached on clean fits by widths the views do not constrain (the clavicle's
    and the foot's x scale on the development set).
    """
    hi = bounds[1]
    return [
        f"scale {name} = {s:.2f} at its upper bound {hi}"
        for name, s in zip(names, scales, strict=True)
        if s >= hi * (1 - tol)
    ]
