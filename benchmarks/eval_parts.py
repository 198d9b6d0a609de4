"""Accuracy of the stereo part decomposition on synthetic subjects with truth.

    python benchmarks/eval_parts.py --data DIR [--config configs/stereo.yaml] [--set KEY=VALUE]

For every subject with a stereo pair and ``truth.json``: measure it (tools/measure_stereo.py's
pipeline) and compare the 3-D joints with ``joints_world.stereo`` (mm) and the lengths with
truth (%). Prints a per-joint and per-length table (mean over measured subjects), the failure
rate with the rule that failed per subject, machine and versions. Figures are over the subjects
whose rules succeeded; failed subjects are listed, never scored.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import scipy
import torch
from tqdm import tqdm

from torchfit.config import load_config
from torchfit.io.dataset import load_dataset
from torchfit.parts import STEREO_MEASUREMENT_KEYS
from torchfit.pipeline.stereo import measure_stereo_pair

JOINTS = (
    "back", "neck", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist", "r_wrist",
)  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, type=Path)
    p.add_argument("--config", type=Path, default=Path("configs/stereo.yaml"))
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    config = load_config(args.config, args.set)
    subjects = [s for s in load_dataset(args.data) if s.stereo is not None and s.truth]
    joint_err: dict[str, list[float]] = {j: [] for j in JOINTS}
    length_err: dict[str, list[float]] = {k: [] for k in STEREO_MEASUREMENT_KEYS}
    failures = []
    start = time.perf_counter()
    for subject in tqdm(subjects, desc="eval", unit="subject"):
        result = measure_stereo_pair(subject.stereo, config.parts, config.segmentation)
        if result.status != "ok":
            failures.append((subject.name, result.failed_rule, result.message))
            continue
        truth_joints = subject.truth["joints_world"]["stereo"]
        for j in JOINTS:
            if j in result.joints_world:
                d = np.subtract(result.joints_world[j], truth_joints[j])
                joint_err[j].append(1000 * float(np.linalg.norm(d)))
        for k, v in result.measurements.items():
            if k in subject.truth:
                length_err[k].append(100 * (v - subject.truth[k]) / subject.truth[k])
    seconds = time.perf_counter() - start
    n_ok = len(subjects) - len(failures)
    print(
        f"\ndataset {args.data}: {len(subjects)} subjects, {n_ok} measured, {len(failures)} failed"
    )
    print(f"config {args.config} {' '.join(args.set)}")
    print(f"\n{'joint':12s} {'n':>3s} {'mean mm':>8s} {'median':>7s} {'max':>7s}")
    all_j = []
    for j, e in joint_err.items():
        if e:
            all_j += e
            print(f"{j:12s} {len(e):3d} {np.mean(e):8.1f} {np.median(e):7.1f} {np.max(e):7.1f}")
    if all_j:
        print(f"{'ALL':12s} {len(all_j):3d} {np.mean(all_j):8.1f} {np.median(all_j):7.1f}")
    print(f"\n{'length':14s} {'n':>3s} {'mean |%|':>9s} {'bias %':>7s} {'max |%|':>8s}")
    for k, e in length_err.items():
        if e:
            a = np.abs(e)
            print(f"{k:14s} {len(e):3d} {a.mean():9.2f} {np.mean(e):+7.2f} {a.max():8.2f}")
    print(f"\nfailures ({len(failures)}/{len(subjects)}):", dict(Counter(f[1] for f in failures)))
    for name, rule, msg in failures:
        print(f"  {name}: {rule}: {msg}")
    machine = platform.processor() or platform.machine()
    print(
        f"\n{seconds / max(len(subjects), 1):.2f} s/subject; {machine}"
        f", python {platform.python_version()}, torch {torch.__version__}, numpy {np.__version__}"
        f", scipy {scipy.__version__}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
