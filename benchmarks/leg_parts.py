"""Where a fitted lower leg's error comes from: the ankle's height, or the shank's length.

A diagnostic, not a method: it reads ``truth.json``. design.md's ``lower_leg_m`` is the
floor-to-knee height in the neutral pose, two parts of which no posture shows as an edge:
where the ankle joint sits above the sole, and where the knee sits on the leg. For every
subject of a benchmark run it takes the fitted model's neutral pose (``params.json``'s segment
scales, standing on the floor) and the truth's standing posture (``joints_world["pose1"]``:
feet flat on the floor, legs straight) and prints, in millimetres, fitted minus true:

- ``ankle``: the ankles' mean height above the floor;
- ``shank``: the knee's height above the ankle (the shank's vertical length);
- ``knee``: the knee's height, against the truth's ``lower_leg_m`` (the sum of the two, less
  the few millimetres the standing posture's knees take from the neutral pose);
- ``hip``: the hips' height.

Then each column's mean and standard deviation over the subjects, and, from the same truth,
the ankle's height as a share of the stature: the template's, the set's bodies', and ANSUR II's
lateral malleolus height over stature (``../shared/data/ansur2`` where it is present).

    python benchmarks/leg_parts.py --data <dev set> --run <benchmark run folder>

Only for development sets: it uses their truth.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from torchfit.body import BodyModel
from torchfit.body.measure import neutral_joints as measured_neutral

ROOT = Path(__file__).resolve().parents[1]
ANSUR = ROOT.parent / "shared" / "data" / "ansur2"
COLUMNS = ("ankle", "shank", "knee", "hip")


def _mean_height(joints: dict, name: str) -> float:
    return 0.5 * (float(joints[f"l_{name}"][2]) + float(joints[f"r_{name}"][2]))


def neutral_joints(model: BodyModel, scales: dict) -> dict[str, np.ndarray]:
    """The model's joints in its neutral pose with these segment scales (``params.json``'s
    ``segment_scales``), soles on the floor (:func:`torchfit.body.measure.neutral_joints`)."""
    s = torch.tensor([scales[n] for n in model.template.segments], dtype=model.dtype)[None]
    return {k: v[0].numpy() for k, v in measured_neutral(model, s).items()}


def subject_row(model: BodyModel, fitted: dict, truth: dict) -> dict[str, float]:
    """Fitted minus true, millimetres (see the module doc)."""
    fit = neutral_joints(model, fitted["segment_scales"])
    true = truth["joints_world"]["pose1"]
    out = {
        "ankle": _mean_height(fit, "ankle") - _mean_height(true, "ankle"),
        "shank": (_mean_height(fit, "knee") - _mean_height(fit, "ankle"))
        - (_mean_height(true, "knee") - _mean_height(true, "ankle")),
        "knee": _mean_height(fit, "knee") - truth["lower_leg_m"],
        "hip": _mean_height(fit, "hip") - _mean_height(true, "hip"),
    }
    return {k: 1000.0 * v for k, v in out.items()}


def ankle_shares(model: BodyModel, data: Path) -> dict[str, float]:
    """The ankle's height over the stature: the template's, the set's, ANSUR II's."""
    ones = {n: [1.0, 1.0, 1.0] for n in model.template.segments}
    t = neutral_joints(model, ones)
    out = {"template": _mean_height(t, "ankle") / float(t["head_top"][2])}
    shares = []
    for path in sorted(data.glob("subject_*/truth.json")):
        truth = json.loads(path.read_text())
        shares.append(_mean_height(truth["joints_world"]["pose1"], "ankle") / truth["height_m"])
    out["set"] = float(np.mean(shares))
    if ANSUR.is_dir():
        sys.path.insert(0, str(ROOT / "tools"))
        from make_proportions import read_ansur

        cols = read_ansur(ANSUR, ("stature", "lateralmalleolusheight"))
        out["ANSUR II"] = float(np.mean(cols["lateralmalleolusheight"] / cols["stature"]))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, type=Path, help="the set (with truth.json)")
    parser.add_argument("--run", required=True, type=Path, help="a benchmark run folder")
    args = parser.parse_args(argv)
    rows, models = {}, {}
    for path in sorted(args.run.glob("subject_*/params.json")):
        fitted = json.loads(path.read_text())
        if fitted["template"] not in models:
            models[fitted["template"]] = BodyModel(fitted["template"], dtype=torch.float64)
        model = models[fitted["template"]]
        truth = json.loads((args.data / path.parent.name / "truth.json").read_text())
        rows[path.parent.name] = subject_row(model, fitted, truth)
    if not rows:
        print(f"no subject_*/params.json under {args.run}", file=sys.stderr)
        return 2
    print("subject       " + "".join(f"{c:>8s}" for c in COLUMNS) + "   (fitted - true, mm)")
    for name, row in rows.items():
        print(f"{name:14s}" + "".join(f"{row[c]:+8.1f}" for c in COLUMNS))
    table = np.array([[row[c] for c in COLUMNS] for row in rows.values()])
    print("mean          " + "".join(f"{v:+8.1f}" for v in table.mean(0)))
    print("sd            " + "".join(f"{v:8.1f}" for v in table.std(0)))
    shares = ankle_shares(model, args.data)
    print("ankle height / stature: " + ", ".join(f"{k} {v:.4f}" for k, v in shares.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
