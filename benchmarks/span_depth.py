"""Where a fitted arm span's error comes from: the T-pose image, or the depth the fit gives it.

A diagnostic, not a method: it reads ``truth.json`` and ``truth_masks/``. For every subject of
a benchmark run it prints, in percent:

- ``span``: the fitted arm span's error against the truth;
- ``image``: the true T-pose silhouette's width (``truth_masks/pose4.png``, leftmost to
  rightmost pixel) times the true depth of the shoulders and wrists over the focal length,
  against the true span: what the T-pose image alone shows when its depth is known;
- ``depth``: the mean depth along the camera's axis of the fitted model's hips and shoulders
  in posture 4 (posed from ``params.json``, standing on the floor) against the true joints':
  how far the fit placed the person from the camera in the T-pose (the template's joint
  centres and the generator's are not defined alike, so a few millimetres of it may be
  definitions);
- ``ratio``: the true arm span over the true height.

Then the correlations of ``span`` with the other three, and of ``depth`` with ``ratio``, over
the subjects.

    python benchmarks/span_depth.py --data <dev set> --run <benchmark run folder>

Only for development sets: it uses their truth.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import cv2
import numpy as np
import torch

from torchfit.body import BodyModel
from torchfit.camera import Camera, world_to_camera
from torchfit.io import load_camera

#: the joints whose depth is the torso's
TORSO = ("l_hip", "r_hip", "l_shoulder", "r_shoulder")


def posed_joints(model: BodyModel, params: dict, pose: str) -> dict[str, np.ndarray]:
    """World joint positions (metres) of a fitted subject's posture ``pose`` (``"pose4"``)
    from its ``params.json``, standing on the floor (the lower sole at z = 0)."""
    record = params["poses"][pose]
    scales = torch.tensor(
        [params["segment_scales"][name] for name in model.template.segments], dtype=model.dtype
    )[None]
    angles = model.zeros(1)["joint_angles"].clone()
    for name, value in record["joint_angles"].items():
        angles[:, model.dof_index(name)] = value
    rotation = torch.as_tensor(record["root_rotation"], dtype=model.dtype)[None]
    translation = torch.tensor(
        [[*map(float, record["root_translation_xy"]), 0.0]], dtype=model.dtype
    )
    joints = model.joint_positions(model(scales, angles, translation, rotation))
    floor = min(float(joints["l_sole"][0, 2]), float(joints["r_sole"][0, 2]))
    return {k: v[0].numpy() - np.array([0.0, 0.0, floor]) for k, v in joints.items()}


def _mean_depth(points: list, camera: Camera) -> float:
    """Mean depth along the camera's axis of world points (metres)."""
    world = torch.tensor(np.asarray(points, dtype=np.float64)[None], dtype=camera.R.dtype)
    return float(world_to_camera(world, camera)[0, :, 2].mean())


def subject_row(subject: Path, fitted: dict, model: BodyModel) -> dict[str, float]:
    """The four figures of one subject (see the module docstring); ``fitted`` holds its
    ``params`` and ``measurements``, ``model`` is the fit's template body."""
    truth = json.loads((subject / "truth.json").read_text())
    camera = load_camera(subject / "camera.yaml")
    focal = float(camera.K[0, 0, 0])
    joints = truth["joints_world"]["pose4"]
    depth = _mean_depth(
        [joints[k] for k in ("l_wrist", "r_wrist", "l_shoulder", "r_shoulder")], camera
    )
    mask = cv2.imread(str(subject / "truth_masks" / "pose4.png"), cv2.IMREAD_GRAYSCALE) > 127
    columns = np.nonzero(mask.any(0))[0]
    width_m = (columns.max() - columns.min() + 1) * depth / focal
    posed = posed_joints(model, fitted["params"], "pose4")
    fit_depth = _mean_depth([posed[k] for k in TORSO], camera)
    true_depth = _mean_depth([joints[k] for k in TORSO], camera)
    span = truth["arm_span_m"]
    return {
        "span": 100 * (fitted["measurements"]["arm_span_m"] / span - 1),
        "image": 100 * (width_m / span - 1),
        "depth": 100 * (fit_depth / true_depth - 1),
        "ratio": span / truth["height_m"],
    }


def data_and_run(argv: list[str] | None, description: str) -> tuple[Path, Path]:
    """The ``--data`` (development set) and ``--run`` (benchmark folder) of a diagnostic."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--data", required=True, help="the development set the run fitted")
    p.add_argument("--run", required=True, help="the benchmark's output folder")
    args = p.parse_args(argv)
    return Path(args.data), Path(args.run)


def fitted_subjects(run: Path):
    """Per subject of a benchmark run that was fitted (not ``failed``, with a params.json):
    its name, status and folder, in ``summary.csv``'s order."""
    with open(run / "summary.csv") as f:
        for line in csv.DictReader(f):
            folder = run / line["subject"]
            if line["status"] != "failed" and (folder / "params.json").is_file():
                yield line["subject"], line["status"], folder


def main(argv: list[str] | None = None) -> int:
    data, run = data_and_run(argv, __doc__.splitlines()[0])
    rows, models = {}, {}
    for subject, status, folder in fitted_subjects(run):
        fitted = {
            "params": json.loads((folder / "params.json").read_text()),
            "measurements": json.loads((folder / "measurements.json").read_text()),
        }
        name = fitted["params"]["template"]
        if name not in models:  # one model per template, not per subject
            models[name] = BodyModel(name)
        rows[subject] = (status, subject_row(data / subject, fitted, models[name]))
    if len(rows) < 3:
        raise SystemExit("error: fewer than 3 fitted subjects with truth")
    print(f"{'subject':12s} {'status':9s} {'span':>7s} {'image':>7s} {'depth':>7s} {'ratio':>6s}")
    for name, (status, r) in rows.items():
        print(
            f"{name:12s} {status:9s} {r['span']:+7.2f} {r['image']:+7.2f} {r['depth']:+7.2f}"
            f" {r['ratio']:6.3f}"
        )
    table = {k: np.array([r[k] for _, r in rows.values()]) for k in ("span", "image", "depth")}
    ratio = np.array([r["ratio"] for _, r in rows.values()])
    print(
        f"mean |error| %: span {np.abs(table['span']).mean():.2f}, image "
        f"{np.abs(table['image']).mean():.2f}, depth {np.abs(table['depth']).mean():.2f}"
    )
    for name, other in (("image", table["image"]), ("depth", table["depth"]), ("ratio", ratio)):
        print(f"correlation of span with {name}: {np.corrcoef(table['span'], other)[0, 1]:+.2f}")
    print(f"correlation of depth with ratio: {np.corrcoef(table['depth'], ratio)[0, 1]:+.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
