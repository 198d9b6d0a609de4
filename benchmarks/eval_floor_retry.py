"""Silhouettes that lose their legs: how often, and what a second segmentation gives back.

For every posture of every subject (synthetic sets with `truth_masks/`) whose silhouette does
not reach the floor (`segmentation.floor_reach_m`, torchfit.pipeline.prepare.floor_reach),
this prints the IoU with the true silhouette and the distance from the mark at which the
lowest pixel sees the floor. It does so for the first segmentation and for the second attempt
of `segmentation.floor_retry`, with the shadow test confined to each band of `--bands` (1 = no
confinement) and with the bridge. Means are over the postures found.

    python benchmarks/eval_floor_retry.py --data DIR [DIR ...] [--config configs/benchmark.yaml]
        [--bands 1,0.25,0.15]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from torchfit.config.loader import load_config
from torchfit.image import fit_background, segment
from torchfit.io.dataset import load_subject
from torchfit.io.images import load_frames
from torchfit.pipeline.prepare import floor_reach, floor_retry_options


def _iou(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a & b).sum()) / max(float((a | b).sum()), 1.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, nargs="+", required=True)
    parser.add_argument("--config", default="configs/benchmark.yaml")
    parser.add_argument("--bands", default="1,0.25,0.15")
    args = parser.parse_args()
    seg = load_config(args.config).segmentation
    limit = seg.floor_reach_m if seg.floor_reach_m is not None else 1.0
    variants = {"first": seg}
    for band in (float(b) for b in args.bands.split(",")):
        variants[f"band {band:g} + bridge"] = floor_retry_options(seg, band)
    found: list[list[tuple[float, float]]] = []
    subjects = affected = 0
    for root in args.data:
        for folder in sorted(p for p in root.iterdir() if (p / "truth_masks").is_dir()):
            subjects += 1
            subject = load_subject(folder)
            background, _ = load_frames(subject.background)
            images, _ = load_frames(subject.poses)
            model = fit_background(background, seg)
            first = segment(images, model, seg).masks[:, 0]
            reach = floor_reach(first, subject.camera)
            short = [j for j, d in enumerate(reach) if not d <= limit]
            affected += bool(short)
            for j in short:
                truth = cv2.imread(str(folder / "truth_masks" / f"pose{j + 1}.png"), 0) > 127
                truth = torch.from_numpy(truth)
                row = []
                for options in variants.values():
                    mask = segment(images[j : j + 1], model, options).masks[0, 0]
                    row.append((_iou(mask, truth), floor_reach(mask[None], subject.camera)[0]))
                found.append(row)
                cells = "  ".join(f"{i:.3f} / {d:.2f} m" for i, d in row)
                print(f"{root.name}/{folder.name} pose{j + 1}: {cells}", flush=True)
    print(
        f"\n{subjects} subjects, {affected} with a posture not reaching the floor "
        f"(> {limit:g} m), {len(found)} postures"
    )
    if found:
        table = np.array(found)  # (N, V, 2)
        for k, name in enumerate(variants):
            reached = int((table[:, k, 1] <= limit).sum())
            print(
                f"{name:>22}: mean IoU {table[:, k, 0].mean():.3f}, "
                f"reaching the floor {reached}/{len(found)}"
            )


if __name__ == "__main__":
    main()
