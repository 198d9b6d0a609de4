"""How far the fitted body's joints lie from the true ones in the six postures themselves.

A diagnostic, not a method: it reads ``truth.json``. For every subject of a benchmark run,
each posture is posed from ``params.json`` (standing on the floor, as
:func:`span_depth.posed_joints` poses it) and its joints (design.md's, but ``head_top``) are
compared with the truth's ``joints_world.pose<k>``. Per posture it prints, in millimetres:

- the mean distance, and its parts along the camera's ray through the true joint and across
  it (what the silhouette shows: across; what it hardly shows: along);
- the mean signed part along the ray (positive: further from the camera than the truth);
- the spread of the trunk's depth over the subjects (the standard deviation of the mean
  signed along-ray error of the hips, shoulders, back and neck: where the fit placed the
  whole body along the ray);
- the mean and largest height of the higher sole above the floor (the lower one touches it):
  a leg swung along the ray lifts its foot while the outline hardly changes. The truth's
  ankles are compared too (the generator drops the lowest point of its body onto the floor,
  so its own feet float a little where a posture's joint angles differ left to right);
- the signed height of the posed head top above the floor, fitted less true, and the
  posture's fold, fitted and true: the reported height (the neutral body's, from
  ``measurements.json`` and ``truth.json``) less the posed head top's height. A fitted body
  that folds more than the truth (a lean, hips or knees bent along the ray, none of which the
  outline shows) is reported taller than it stands in the images.

    python benchmarks/posture_joints.py --data <dev set> --run <benchmark run folder>

Only for development sets: it uses their truth. The tracker's joints can only be as near as
these are where the silhouette is the same (``tools/track.py`` fits the same body).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from span_depth import data_and_run, fitted_subjects, posed_joints  # noqa: E402

from torchfit.body import BodyModel  # noqa: E402
from torchfit.camera import camera_centre  # noqa: E402
from torchfit.io import load_camera  # noqa: E402
from torchfit.measurements import JOINT_NAMES  # noqa: E402

JOINTS = [n for n in JOINT_NAMES if n != "head_top"]
TRUNK = ("back", "neck", "l_shoulder", "r_shoulder", "l_hip", "r_hip")


def posture_errors(model: BodyModel, params: dict, truth: dict, centre: np.ndarray, pose: str):
    """One subject's posture ``pose``: per joint the error vector (J, 3) split into its signed
    part along the camera's ray through the true joint (J,) and its part across it (J,), the
    fitted soles' heights (2,) and the fitted head top's height."""
    fitted = posed_joints(model, params, pose)
    true = truth["joints_world"][pose]
    diff = np.array([fitted[n] - np.asarray(true[n]) for n in JOINTS])
    rays = np.array([np.asarray(true[n]) - centre for n in JOINTS])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    along = (diff * rays).sum(1)
    across = np.linalg.norm(diff - along[:, None] * rays, axis=1)
    soles = np.array([fitted["l_sole"][2], fitted["r_sole"][2]])
    return diff, along, across, soles, fitted["head_top"][2]


def main(argv: list[str] | None = None) -> int:
    data, run = data_and_run(argv, __doc__.splitlines()[0])
    rows: dict[str, list] = {}
    model = None
    for subject, _, folder in fitted_subjects(run):
        params = json.loads((folder / "params.json").read_text())
        model = model or BodyModel(params["template"])
        truth = json.loads((data / subject / "truth.json").read_text())
        camera = load_camera(data / subject / "camera.yaml")
        height = json.loads((folder / "measurements.json").read_text())["height_m"]
        centre = camera_centre(camera.R, camera.t)[0].double().numpy()
        for pose in sorted(truth["joints_world"]):
            if pose in params["poses"]:
                *got, top = posture_errors(model, params, truth, centre, pose)
                true = truth["joints_world"][pose]
                ankles = abs(true["l_ankle"][2] - true["r_ankle"][2])
                tops = (
                    top - true["head_top"][2],
                    height - top,
                    truth["height_m"] - true["head_top"][2],
                )
                rows.setdefault(pose, []).append((*got, ankles, tops))
    if not rows:
        raise SystemExit("error: no fitted subject with truth")
    trunk = [JOINTS.index(n) for n in TRUNK]
    print(
        f"{'posture':8s} {'n':>3s} {'mean':>6s} {'along':>6s} {'across':>6s} {'signed':>7s} "
        f"{'trunk sd':>8s} {'sole mean/max':>14s} {'true ankles dz':>14s} "
        f"{'head top':>8s} {'fold fit/true':>14s}"
    )
    every = []
    for pose, got in rows.items():
        norm = np.array([np.linalg.norm(d, axis=1) for d, *_ in got]) * 1000
        along = np.array([a for _, a, *_ in got]) * 1000
        across = np.array([c for _, _, c, *_ in got]) * 1000
        float_mm = np.array([s.max() - s.min() for *_, s, _, _ in got]) * 1000
        true_dz = np.array([t for *_, t, _ in got]) * 1000
        top, fold, true_fold = (np.array([row[-1] for row in got]) * 1000).mean(0)
        every.append((norm, along, across))
        print(
            f"{pose:8s} {len(got):3d} {norm.mean():6.1f} {np.abs(along).mean():6.1f} "
            f"{across.mean():6.1f} {along.mean():+7.1f} {along[:, trunk].mean(1).std():8.1f} "
            f"{float_mm.mean():6.1f} / {float_mm.max():5.1f} {true_dz.mean():8.1f} mm "
            f"{top:+8.1f} {fold:6.1f} / {true_fold:5.1f} mm"
        )
    norm, along, across = (np.concatenate([e[k].ravel() for e in every]) for k in range(3))
    print(
        f"all postures: mean {norm.mean():.1f} mm, along the rays {np.abs(along).mean():.1f}, "
        f"across {across.mean():.1f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
