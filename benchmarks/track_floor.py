"""The model's floor on a tracked sequence: the best joint error any pose of the fitted model
reaches, with the truth known.

    python benchmarks/track_floor.py --model RUN/SUBJECT --sequence SEQ_DIR [--every 5]

For every ``--every``-th frame of the sequence's ``truth.json``, the root and joint angles of
the fitted model (its scales fixed, the joint angles within the template's limits) are fitted
to the true joint positions directly (``scipy.optimize.least_squares``, bounded trust region,
from the previous frame's pose and from the neutral pose, the better kept; a 0.01 m/rad pull
of the joint angles towards 0 keeps unseen twists at rest). What remains is what the model
cannot express: its joint definitions against the body's (template against the generator's
skeleton), its proportions and its joint limits. A tracker's error above this floor is the
tracker's own. Prints per frame and the mean, in mm, over design.md's joints but head_top.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import least_squares

from torchfit.body.model import BodyModel
from torchfit.measurements import JOINT_NAMES
from torchfit.pipeline.track import load_fitted


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True, help="fitted subject folder (params.json)")
    p.add_argument("--sequence", required=True, help="sequence folder with truth.json")
    p.add_argument("--every", type=int, default=5)
    args = p.parse_args()
    template, scales = load_fitted(args.model)
    model = BodyModel(template)
    sc = torch.tensor([scales[s] for s in model.template.segments], dtype=torch.float64)[None]
    truth = json.loads((Path(args.sequence) / "truth.json").read_text())["joints_world"]
    names = [n for n in JOINT_NAMES if n != "head_top"]
    q = model.num_dofs
    lower = np.r_[[-np.inf] * 6, model.joint_lower.numpy()]
    upper = np.r_[[np.inf] * 6, model.joint_upper.numpy()]

    def inside(x: np.ndarray) -> np.ndarray:
        return np.clip(x, lower + 1e-9, upper - 1e-9)

    x = np.zeros(6 + q)
    errors = []
    for f in range(0, len(truth), args.every):
        target = np.array([truth[f][n] for n in names])
        if f == 0:
            x[:3] = target.mean(0)

        def residual(row: np.ndarray, target: np.ndarray = target) -> np.ndarray:
            xt = torch.from_numpy(row[None])
            with torch.no_grad():
                out = model(sc, xt[:, 6:], xt[:, :3], xt[:, 3:6])
                joints = model.joint_positions(out)
            posed = np.stack([joints[n][0].numpy() for n in names])
            return np.r_[(posed - target).ravel(), 1e-2 * row[6:]]

        starts = [inside(x), inside(np.r_[x[:6], np.zeros(q)])]
        fits = [least_squares(residual, s, bounds=(lower, upper), max_nfev=3000) for s in starts]
        x = min(fits, key=lambda r: r.cost).x
        per_joint = 1000 * np.linalg.norm(residual(x)[: 3 * len(names)].reshape(-1, 3), axis=1)
        errors.append(per_joint)
        print(f"frame {f}: {per_joint.mean():.1f} mm", flush=True)
    errors = np.array(errors)
    print(
        json.dumps(
            {
                "floor_mm": round(float(errors.mean()), 1),
                "per_joint_mm": {
                    n: round(float(v), 1) for n, v in zip(names, errors.mean(0), strict=True)
                },
                "frames": len(errors),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
