"""Derive the human body-proportion ranges the judge checks a fit against, from ANSUR II.

    python tools/make_proportions.py [--ansur ../shared/data/ansur2] [--out FILE]

(``--out`` defaults to ``torchfit/pipeline/proportions.csv``.)

Each row is a fitted measurement divided by the height, with the ANSUR II columns that stand
for it (millimetres, divided by ``stature``), its 0.5th, 1st, 99th and 99.5th percentiles and
its geometric mean over all 6068 soldiers (men and women together). ANSUR II measures
landmarks on the skin (acromion, radiale, stylion, tibiale), the model joint centres: how the
judge reads each row is its ``convention`` (``torchfit.pipeline.checks``).
``tests/pipeline/test_checks.py`` re-derives the table where the data are present.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: measurement key -> (ANSUR II expression, columns added with their signs, convention):
#: ``same`` where ANSUR II measures what the model does (fingertip to fingertip), ``template``
#: where it measures skin landmarks and the model joint centres (the judge then reads the
#: ratio relative to its geometric mean and puts the template there, as the prior does).
RATIOS: dict[str, tuple[str, dict[str, int], str]] = {
    "arm_span_m": ("span", {"span": 1}, "same"),
    "upper_arm_m": ("acromionradialelength", {"acromionradialelength": 1}, "template"),
    "forearm_m": ("radialestylionlength", {"radialestylionlength": 1}, "template"),
    "lower_leg_m": ("tibialheight", {"tibialheight": 1}, "template"),
    "thigh_m": (
        "trochanterionheight - tibialheight",
        {"trochanterionheight": 1, "tibialheight": -1},
        "template",
    ),
    "shoulder_width_m": ("biacromialbreadth", {"biacromialbreadth": 1}, "template"),
}
#: The hard limits (0.5th, 99.5th) and the population range (1st, 99th) of each ratio.
PERCENTILES = (0.5, 1.0, 99.0, 99.5)


def read_ansur(folder: Path, wanted: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """Columns of both ANSUR II files, men and women stacked (lower-case names, millimetres).

    ``wanted`` names the columns (default: ``stature`` and those of :data:`RATIOS`); the
    result also holds ``sex``, ``"male"`` or ``"female"`` per row.
    """
    if wanted is None:
        wanted = ("stature", *sorted({c for _, cols, _ in RATIOS.values() for c in cols}))
    columns: dict[str, list] = {}
    for name, encoding in (("MALE", "latin-1"), ("FEMALE", "utf-8")):
        with (folder / f"ANSUR_II_{name}_Public.csv").open(encoding=encoding) as f:
            for row in csv.DictReader(f):
                for key in wanted:
                    columns.setdefault(key, []).append(float(row[key]))
                columns.setdefault("sex", []).append(name.lower())
    return {k: np.asarray(v) for k, v in columns.items()}


def derive(folder: Path) -> list[dict[str, str]]:
    """The table rows: measurement, ANSUR expression, convention, percentiles and geometric
    mean of the ratio to stature."""
    data = read_ansur(folder)
    rows = []
    for key, (expression, cols, convention) in RATIOS.items():
        ratio = sum(sign * data[c] for c, sign in cols.items()) / data["stature"]
        p0_5, p1, p99, p99_5 = np.percentile(ratio, PERCENTILES)
        rows.append(
            {
                "measurement": key,
                "ansur": f"({expression}) / stature",
                "convention": convention,
                "p0_5": f"{p0_5:.4f}",
                "p1": f"{p1:.4f}",
                "gmean": f"{np.exp(np.log(ratio).mean()):.4f}",
                "p99": f"{p99:.4f}",
                "p99_5": f"{p99_5:.4f}",
                "n": str(ratio.size),
            }
        )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--ansur",
        type=Path,
        default=ROOT.parent / "shared" / "data" / "ansur2",
        help="folder of the ANSUR II CSV files (default ../shared/data/ansur2)",
    )
    default_out = ROOT / "torchfit" / "pipeline" / "proportions.csv"
    parser.add_argument(
        "--out",
        type=Path,
        default=default_out,
        help="the table to write (default: the shipped torchfit/pipeline/proportions.csv)",
    )
    args = parser.parse_args()
    if not (args.ansur / "ANSUR_II_MALE_Public.csv").is_file():
        sys.stderr.write(f"no ANSUR II files in {args.ansur}\n")
        return 2
    rows = derive(args.ansur)
    with args.out.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
