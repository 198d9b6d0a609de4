"""The model's floor on a tracked sequence: the best joint error any pose of the fitted model
reaches, with the truth known.

    python benchmarks/track_floor.py --model RUN/SUBJECT --sequence SEQ_DIR [--every 5] \
        [--settle] [--track OUT] [--config configs/track.yaml] [--set KEY=VALUE ...]

For every ``--every``-th frame of the sequence's ``truth.json``, the root and joint angles of
the fitted model (its scales fixed, the joint angles within the template's limits) are fitted
to the true joint positions directly (``scipy.optimize.least_squares``, bounded trust region,
from the previous frame's pose and from the neutral pose, the better kept; a 0.01 m/rad pull
of the joint angles towards 0 keeps unseen twists at rest). What remains is what the model
cannot express: its joint definitions against the body's (template against the generator's
skeleton), its proportions and its joint limits. A tracker's error above this floor is the
tracker's own. Prints per frame and the mean, in mm, over design.md's joints but head_top.

``--settle`` asks where the tracker's own objective holds a pose that starts on this floor:
each sampled frame is segmented as ``tools/track.py`` segments it, and the tracker's frame
solve (:func:`torchfit.track.frame.solve_frame`, ``--config``'s options) starts from the floor
pose with the floor pose as its prediction (a tracker that was right up to the frame before
and whose person stood still). Its error is what the silhouette objective itself moves a
right pose to: a tracker of this objective does not settle nearer the truth by its search.
``settled_free_mm`` is the same with the temporal terms off (the contour, the floor and the
twists' pull alone). ``settled_moved_mm`` starts and predicts from the floor pose of the sampled
frame before instead (with ``--every 1``, the frame before: a tracker right up to then, the
person moving on as they did).

``--track OUT`` tracks the whole sequence as ``tools/track.py`` does (``--config``), but with the
first frame started from its floor pose instead of the tracker's own start
(:func:`torchfit.track.start_poses`), and writes the outputs to ``OUT``: the error left with a
right first frame is the tracker's drift.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import least_squares

from torchfit.body.model import BodyModel
from torchfit.camera import stack_cameras
from torchfit.config import load_config
from torchfit.image import fit_background, segment
from torchfit.io.images import load_frames
from torchfit.measurements import JOINT_NAMES
from torchfit.pipeline.track import TrackConfig, load_fitted, load_sequence, track_sequences
from torchfit.track import PoseLayout, frame_data
from torchfit.track.frame import solve_frame

NAMES = [n for n in JOINT_NAMES if n != "head_top"]


def joint_residual(model: BodyModel, sc: torch.Tensor, row: np.ndarray, target: np.ndarray):
    """The pose row's joints less the target joints (metres, flat), then the 0.01 m/rad pull of
    its joint angles towards 0."""
    xt = torch.from_numpy(row[None])
    with torch.no_grad():
        joints = model.joint_positions(model(sc, xt[:, 6:], xt[:, :3], xt[:, 3:6]))
    posed = np.stack([joints[n][0].numpy() for n in NAMES])
    return np.r_[(posed - target).ravel(), 1e-2 * row[6:]]


def joint_error_mm(model, sc, row: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Per joint (NAMES), the distance in mm of the pose row's joint from the target's."""
    return 1000 * np.linalg.norm(
        joint_residual(model, sc, row, target)[: 3 * len(NAMES)].reshape(-1, 3), axis=1
    )


def floor_pose(model: BodyModel, sc: torch.Tensor, target: np.ndarray, x: np.ndarray):
    """The pose row (root translation, rotation, joint angles within the limits) whose joints
    best fit ``target`` (J, 3), from ``x`` and from ``x``'s root with the joints at 0."""
    q = model.num_dofs
    lower = np.r_[[-np.inf] * 6, model.joint_lower.numpy()]
    upper = np.r_[[np.inf] * 6, model.joint_upper.numpy()]
    starts = [x, np.r_[x[:6], np.zeros(q)]]
    fits = [
        least_squares(
            lambda row: joint_residual(model, sc, row, target),
            np.clip(s, lower + 1e-9, upper - 1e-9),
            bounds=(lower, upper),
            max_nfev=3000,
        )
        for s in starts
    ]
    return min(fits, key=lambda r: r.cost).x


def _mean_per_joint(values: list[np.ndarray]) -> dict[str, float]:
    mean = np.mean(values, axis=0)
    return {n: round(float(v), 1) for n, v in zip(NAMES, mean, strict=True)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, help="fitted subject folder (params.json)")
    p.add_argument("--sequence", required=True, help="sequence folder with truth.json")
    p.add_argument("--every", type=int, default=5)
    p.add_argument("--settle", action="store_true", help="solve the tracker's frame from it")
    p.add_argument("--track", default=None, help="track from frame 0's floor pose into OUT")
    p.add_argument("--config", default="configs/track.yaml")
    p.add_argument("--set", action="append", default=[], help="KEY=VALUE config override")
    args = p.parse_args()
    template, scales, _, _ = load_fitted(args.model)
    model = BodyModel(template)
    sc = torch.tensor([scales[s] for s in model.template.segments], dtype=torch.float64)[None]
    truth = json.loads((Path(args.sequence) / "truth.json").read_text())["joints_world"]
    config = load_config(args.config, args.set, schema=TrackConfig)
    seq = load_sequence(args.sequence)
    camera = stack_cameras([seq.camera]).to(dtype=torch.float64)
    if args.settle:
        background = fit_background(
            load_frames(seq.background, seq.camera.image_size)[0], config.segmentation
        )
    layout = PoseLayout(model, config.track)
    free = dataclasses.replace(
        config.track,
        temporal_translation=0.0,
        temporal_rotation=0.0,
        temporal_joints=0.0,
        temporal_depth=0.0,
    )
    x0 = np.zeros(layout.num_params)
    x0[:3] = np.mean([truth[0][n] for n in NAMES], axis=0)
    keys = ("floor_mm", "settled_mm", "settled_free_mm", "settled_moved_mm")
    out: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    poses: list[np.ndarray] = []  # the floor pose of each sampled frame
    for f in range(0, len(truth), args.every):
        target = np.array([truth[f][n] for n in NAMES])
        before = poses[-1] if poses else None
        x = floor_pose(model, sc, target, x0 if before is None else before)
        poses.append(x)
        out["floor_mm"].append(joint_error_mm(model, sc, x, target))
        if args.settle:
            image = load_frames([seq.frames[f]], seq.camera.image_size)[0]
            mask = segment(image, background, config.segmentation).masks[0, 0]
            person = frame_data(mask[None], camera, config.track, torch.float64)
            runs = [("settled_mm", x, config.track), ("settled_free_mm", x, free)]
            if before is not None:
                runs.append(("settled_moved_mm", before, config.track))
            for key, start, opts in runs:
                row = torch.from_numpy(start[None].copy())
                res = solve_frame(model, sc, person, layout, row, row, opts)
                out[key].append(joint_error_mm(model, sc, res.x[0].numpy(), target))
        line = ", ".join(f"{k} {v[-1].mean():.1f}" for k, v in out.items() if v)
        print(f"frame {f}: {line}", flush=True)
    doc = {"frames": len(out["floor_mm"])}
    for key, values in out.items():
        if values:
            doc[key] = round(float(np.mean(values)), 1)
            doc[f"{key}_per_joint"] = _mean_per_joint(values)
    if args.track:
        start = torch.from_numpy(poses[0][None].copy())
        (summary,) = track_sequences(model, sc[0], [seq], [Path(args.track)], config, start=start)
        doc["tracked_from_floor_mm"] = round(summary["mean_joint_error_mm"], 1)
        doc["tracked_from_floor_status"] = summary["status"]
    print(json.dumps(doc, indent=1))


if __name__ == "__main__":
    main()
