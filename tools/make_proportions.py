"""Derive the human body-proportion ranges the judge checks a fit against, from ANSUR II.

    python tools/make_proportions.py [--ansur ../shared/data/ansur2] [--out FILE]

(``--out`` defaults to ``torchfit/pipeline/proportions.csv``.)

Each row is a fitted measurement divided by the height, with the ANSUR II columns that stand
for it (millimetres, divided by ``stature``), and its 0.5th and 99.5th percentiles over all
6068 soldiers (men and women together). ANSUR II measures landmarks on the skin (acromion,
radiale, stylion, tibiale), the model joint centres: the judge adds a margin on both sides
(``torchfit.pipeline.checks``). ``tests/pipeline/test_checks.py`` re-derives the table where
the data are present.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: measurement key -> (ANSUR II expression, columns added with their signs)
RATIOS: dict[str, tuple[str, dict[str, int]]] = {
    "arm_span_m": ("span", {"span": 1}),
    "upper_arm_m": ("acromionradialelength", {"acromionradialelength": 1}),
    "forearm_m": ("radialestylionlength", {"radialestylionlength": 1}),
    "lower_leg_m": ("tibialheight", {"tibialheight": 1}),
    "thigh_m": (
        "trochanterionheight - tibialheight",
        {"trochanterionheight": 1, "tibialheight": -1},
    ),
    "shoulder_width_m": ("biacromialbreadth", {"biacromialbreadth": 1}),
}
PERCENTILES = (0.5, 99.5)


def read_ansur(folder: Path, wanted: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """Columns of both ANSUR II files, men and women stacked (lower-case names, millimetres).

    ``wanted`` names the columns (default: ``stature`` and those of :data:`RATIOS`); the
    result also holds ``sex``, ``"male"`` or ``"female"`` per row.
    """
    if wanted is None:
        wanted = ("stature", *sorted({c for _, cols in RATIOS.values() for c in cols}))
    columns: dict[str, list] = {}
    for name, encoding in (("MALE", "latin-1"), ("FEMALE", "utf-8")):
        with (folder / f"ANSUR_II_{name}_Public.csv").open(encoding=encoding) as f:
            for row in csv.DictReader(f):
                for key in wanted:
                    columns.setdefault(key, []).append(float(row[key]))
                columns.setdefault("sex", []).append(name.lower())
    return {k: np.asarray(v) for k, v in columns.items()}


def derive(folder: Path) -> list[dict[str, str]]:
    """The table rows: measurement, ANSUR expression, percentiles of the ratio to stature."""
    data = read_ansur(folder)
    rows = []
    for key, (expression, cols) in RATIOS.items():
        ratio = sum(sign * data[c] for c, sign in cols.items()) / data["stature"]
        lo, hi = np.percentile(ratio, PERCENTILES)
        rows.append(
            {
                "measurement": key,
                "ansur": f"({expression}) / stature",
                "p0_5": f"{lo:.4f}",
                "p99_5": f"{hi:.4f}",
                "n": str(ratio.size),
            }
        )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ansur", type=Path, default=ROOT.parent / "shared" / "data" / "ansur2")
    default_out = ROOT / "torchfit" / "pipeline" / "proportions.csv"
    parser.add_argument("--out", type=Path, default=default_out)
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
