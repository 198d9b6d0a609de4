"""Measure the systematic offsets from the second paper's cut points to the true joint centres.

    python benchmarks/calibrate_parts.py --data <development set> [--config configs/stereo.yaml]

The paper's rules put each joint at a cut middle or a curvature extremum on the outline; the
true joint centre (the skeleton's) lies inside the body, a roughly constant fraction of the
body's size away. For every subject of a synthetic dataset with a stereo pair and a
``truth.json``, this labels both views with all ``parts.offset_*`` set to zero, projects the
true 3-D joints (``joints_world.stereo``) into each view, and expresses true - labelled in the
labelling's own frame: ``down`` along the principal axis and ``out`` away from it on the joint's
side, in units of the 2-D trunk length ``T`` (see :class:`torchfit.parts.JointOffsets`). It
prints the median per joint kind (left and right pooled) and the ``parts:`` lines to paste into
a config.

Run it on the development set only: offsets measured on the subjects you report would be
tuned to them.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from torchfit.config import load_config
from torchfit.io.dataset import load_dataset
from torchfit.parts import JointOffsets, project_joints
from torchfit.parts.rules import joint_kind
from torchfit.pipeline.stereo import measure_stereo_pair

KINDS = ("back", "neck", "shoulder", "elbow", "wrist")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--config", type=Path, default=Path("configs/stereo.yaml"))
    args = parser.parse_args()
    config = load_config(args.config)
    zero = {f"offset_{k}": [0.0, 0.0] for k in KINDS}
    parts = dataclasses.replace(config.parts, **zero)
    samples: dict[str, list[tuple[float, float]]] = {k: [] for k in KINDS}
    used, skipped = 0, []
    for subject in tqdm(load_dataset(args.data), desc="calibrate", unit="subject"):
        truth = (subject.truth or {}).get("joints_world", {}).get("stereo")
        if subject.stereo is None or not truth:
            skipped.append(f"{subject.name}: no stereo pair or no true stereo joints")
            continue
        result = measure_stereo_pair(subject.stereo, parts, config.segmentation)
        if len(result.views) < 2 or not all(v.labelling.ok for v in result.views.values()):
            skipped.append(f"{subject.name}: {result.message or result.failed_rule}")
            continue
        used += 1
        for side, view in result.views.items():
            marks = project_joints(truth, getattr(subject.stereo, side))
            for name in sorted(view.labelling.raw_joints.keys() & marks.keys()):
                samples[joint_kind(name)].append(
                    JointOffsets.measure(view.labelling, name, marks[name])
                )
    for line in skipped:
        print(f"skipped {line}")
    if not used:
        print("error: no subject could be labelled in both views", file=sys.stderr)
        return 2
    print(f"\n{used} subjects, both views; median (down, out) in units of T, with the IQR\n")
    print(f"{'joint':10s} {'n':>4s} {'down':>8s} {'out':>8s}   {'IQR down':>17s} {'IQR out':>17s}")
    lines = []
    for kind in KINDS:
        values = np.array(samples[kind])
        if not len(values):
            continue
        med = np.median(values, axis=0)
        q1, q3 = np.percentile(values, [25, 75], axis=0)
        print(
            f"{kind:10s} {len(values):4d} {med[0]:+8.3f} {med[1]:+8.3f}   "
            f"[{q1[0]:+.3f}, {q3[0]:+.3f}] [{q1[1]:+.3f}, {q3[1]:+.3f}]"
        )
        lines.append(f"  offset_{kind}: [{med[0]:.3f}, {med[1]:.3f}]")
    print("\nparts:\n" + "\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
