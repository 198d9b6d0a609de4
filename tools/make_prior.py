"""Learn the population prior over the template's log scales from ANSUR II.

    python tools/make_prior.py [--ansur ../shared/data/ansur2] [--out FILE]
                               [--calibrate DEV_SET [--template mpeg4_full]]

(``--out`` defaults to ``torchfit/body/priors/ansur2.json``.)

Each prior entry is one template scale (``group:axis``) stood for by an ANSUR II length or
breadth (:data:`ENTRIES`: columns in millimetres, added with their signs). Per component
(``female``, ``male``, and ``any``: either sex with equal weight) the file holds the mean and the
lower Cholesky factor ``L`` of the covariance of the entries' logarithms; the fit adds
``weight * L^-1 (log s - mu)`` to its residuals (``torchfit.fit.prior``).

ANSUR II measures skin landmarks (acromion, radiale, tibiale, trochanterion), the template
joint centres, so the two disagree by a constant factor per entry (about 15 % for the upper
arm). A constant factor shifts the mean of a logarithm but not its covariance, so the file
keeps the covariances as measured and takes the means from the template: every entry's mean is
the mean log stature of the component's people, plus the component's mean log difference from
``any`` for that entry. At the template's own proportions and the population's mean stature
the ``any`` residual is zero; the sexes differ from it by what ANSUR II measures.

``--calibrate DEV_SET`` corrects that assumption where a development set shows it wrong: for
the entries that the report's measurements stand for (:data:`CALIBRATED`), the mean log
proportion of the set's true bodies (``truth.json``, relative to their height) against the
template's own gives a per-entry offset, added to every component's mean (the file's
``calibration`` section). Use a development set only, never the bodies you report on.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from make_proportions import read_ansur  # noqa: E402

from torchfit.fit.prior import SEXES  # noqa: E402  (the prior's components)

ROOT = Path(__file__).resolve().parents[1]

#: template scale entry -> (ANSUR II expression, columns added with their signs)
ENTRIES: dict[str, tuple[str, dict[str, int]]] = {
    "foot:z": ("lateralmalleolusheight", {"lateralmalleolusheight": 1}),
    "foot:x": ("footlength", {"footlength": 1}),
    "calf:z": (
        "tibialheight - lateralmalleolusheight",
        {"tibialheight": 1, "lateralmalleolusheight": -1},
    ),
    "thigh:z": (
        "trochanterionheight - tibialheight",
        {"trochanterionheight": 1, "tibialheight": -1},
    ),
    "pelvis:y": ("hipbreadth", {"hipbreadth": 1}),
    "pelvis:z": (
        "iliocristaleheight - trochanterionheight",
        {"iliocristaleheight": 1, "trochanterionheight": -1},
    ),
    "abdomen:x": ("waistdepth", {"waistdepth": 1}),
    "abdomen:y": ("waistbreadth", {"waistbreadth": 1}),
    "abdomen:z": (
        "chestheight - iliocristaleheight",
        {"chestheight": 1, "iliocristaleheight": -1},
    ),
    "chest:x": ("chestdepth", {"chestdepth": 1}),
    "chest:y": ("chestbreadth", {"chestbreadth": 1}),
    "chest:z": ("cervicaleheight - chestheight", {"cervicaleheight": 1, "chestheight": -1}),
    "neck:z": (
        "stature - tragiontopofhead - cervicaleheight",
        {"stature": 1, "tragiontopofhead": -1, "cervicaleheight": -1},
    ),
    "head:x": ("headlength", {"headlength": 1}),
    "head:y": ("headbreadth", {"headbreadth": 1}),
    "head:z": ("tragiontopofhead", {"tragiontopofhead": 1}),
    "clavicle:y": ("biacromialbreadth", {"biacromialbreadth": 1}),
    "upperarm:z": ("acromionradialelength", {"acromionradialelength": 1}),
    "forearm:z": ("radialestylionlength", {"radialestylionlength": 1}),
    "hand:z": ("handlength", {"handlength": 1}),
}
#: calibrated entry -> the measurement (design.md section 5) whose proportion sets it
CALIBRATED: dict[str, str] = {
    "thigh:z": "thigh_m",
    "calf:z": "lower_leg_m",
    "upperarm:z": "upper_arm_m",
    "forearm:z": "forearm_m",
    "clavicle:y": "shoulder_width_m",
}


def _logs(data: dict[str, np.ndarray]) -> np.ndarray:
    """(N, K) log metres of every entry."""
    cols = [
        sum(sign * data[c] for c, sign in columns.items()) / 1000.0
        for _, columns in ENTRIES.values()
    ]
    values = np.stack(cols, 1)
    if (values <= 0).any():
        raise ValueError("an ANSUR II expression is not positive for some people")
    return np.log(values)


def derive(folder: Path) -> dict:
    """The prior document (see the module docstring)."""
    wanted = sorted({"stature", *(c for _, cols in ENTRIES.values() for c in cols)})
    data = read_ansur(folder, tuple(wanted))
    logs = _logs(data)
    log_stature = np.log(data["stature"] / 1000.0)
    stats = {}
    for sex in SEXES:
        rows = data["sex"] == sex
        stats[sex] = (
            int(rows.sum()),
            logs[rows].mean(0),
            np.cov(logs[rows], rowvar=False),
            float(log_stature[rows].mean()),
        )
    # either sex with equal weight: the moments of the two-component mixture
    (n_f, m_f, c_f, s_f), (n_m, m_m, c_m, s_m) = stats["female"], stats["male"]
    d = m_m - m_f
    stats["any"] = (
        n_f + n_m,
        0.5 * (m_f + m_m),
        0.5 * (c_f + c_m) + 0.25 * np.outer(d, d),
        0.5 * (s_f + s_m),
    )
    any_mean, any_stature = stats["any"][1], stats["any"][3]
    components = {}
    for name, (n, mean, cov, stature) in stats.items():
        components[name] = {
            "n": n,
            "mean_log_stature_m": round(stature, 6),
            "mean": [round(float(v), 6) for v in any_stature + (mean - any_mean)],
            "cholesky": [[round(float(v), 7) for v in row] for row in np.linalg.cholesky(cov)],
        }
    return {
        "name": "ansur2",
        "source": (
            "ANSUR II public release (Gordon et al. 2014, NATICK/TR-15/007): "
            "ANSUR_II_MALE_Public.csv and ANSUR_II_FEMALE_Public.csv"
        ),
        "made_by": "tools/make_prior.py",
        "entries": list(ENTRIES),
        "ansur": {k: expr for k, (expr, _) in ENTRIES.items()},
        "mean_convention": (
            "log metres: the template at unit scales stands for a person of mean stature and "
            "mean proportions (either sex); mu = mean - log(template height)"
        ),
        "components": components,
    }


def calibrate(data: Path, template: str) -> dict:
    """The ``calibration`` section: per-entry log offsets of a development set's true
    proportions from the template's (see the module docstring)."""
    import torch

    sys.path.insert(0, str(ROOT))
    from torchfit.body.measure import measure_model
    from torchfit.body.model import BodyModel

    model = BodyModel(template, dtype=torch.float64)
    ones = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    tmpl = {k: float(v[0]) for k, v in measure_model(model, ones).items()}
    p = model.zeros(1)
    joints = model.joint_positions(
        model(ones, p["joint_angles"], p["root_translation"], p["root_rotation"])
    )
    floor = min(float(joints["l_sole"][0, 2]), float(joints["r_sole"][0, 2]))
    ankle = float(joints["l_ankle"][0, 2]) - floor  # the knee height's part below the calf
    truths = [json.loads(f.read_text()) for f in sorted(data.glob("*/truth.json"))]
    if len(truths) < 3:
        raise ValueError(f"{data}: fewer than 3 subjects with truth.json")
    offsets = {}
    for entry, key in CALIBRATED.items():
        ratios = np.array([t[key] / t["height_m"] for t in truths]) * tmpl["height_m"]
        if key == "lower_leg_m":
            logs = np.log((ratios - ankle) / (tmpl[key] - ankle))
        else:
            logs = np.log(ratios / tmpl[key])
        offsets[entry] = round(float(logs.mean()), 6)
    return {"data": data.name, "subjects": len(truths), "template": template, "offsets": offsets}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--ansur",
        type=Path,
        default=ROOT.parent / "shared" / "data" / "ansur2",
        help="folder of the ANSUR II CSV files (default ../shared/data/ansur2)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=ROOT / "torchfit" / "body" / "priors" / "ansur2.json",
        help="the prior file to write (default: the shipped torchfit/body/priors/ansur2.json)",
    )
    parser.add_argument(
        "--calibrate",
        type=Path,
        help="a development set (subjects with truth.json) to calibrate the prior on",
    )
    parser.add_argument(
        "--template", default="mpeg4_full", help="the template whose scales the prior is over"
    )
    args = parser.parse_args()
    if not (args.ansur / "ANSUR_II_MALE_Public.csv").is_file():
        sys.stderr.write(f"no ANSUR II files in {args.ansur}\n")
        return 2
    args.out.parent.mkdir(parents=True, exist_ok=True)
    doc = derive(args.ansur)
    if args.calibrate is not None:
        doc["calibration"] = calibrate(args.calibrate, args.template)
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
