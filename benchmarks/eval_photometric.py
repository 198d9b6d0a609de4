"""Photometric compensation on real posture images: the demo subjects with their posture
images brightened, darkened or re-white-balanced after capture.

    python benchmarks/eval_photometric.py [--config configs/demo.yaml] [--data data/demo]

For every change (per-channel gains applied to the 8-bit posture images, clipped at 255) and
every posture image of every subject: the F-measure of the silhouette against the one from the
unchanged images, with ``segmentation.photometric`` on and off, the estimated gains (mean over
the images), the share of the image the compensation took from person to background in the
colour test, and how many silhouettes :func:`torchfit.image.implausible` rejects.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
from pathlib import Path

import torch

from torchfit.config import load_config
from torchfit.image import fit_background, implausible, match_background, segment
from torchfit.io import load_frames
from torchfit.io.dataset import load_dataset

REPO = Path(__file__).resolve().parents[1]
CHANGES = [
    (1.03, 1.03, 1.03),
    (0.97, 0.97, 0.97),
    (1.15, 1.15, 1.15),
    (0.85, 0.85, 0.85),
    (1.15, 1.0, 0.85),
    (0.85, 1.0, 1.15),
]


def f_measure(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(2 * (a & b).sum() / (a.sum() + b.sum()).clamp_min(1))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--config", type=Path, default=REPO / "configs" / "demo.yaml")
    p.add_argument("--data", type=Path, default=REPO / "data" / "demo")
    args = p.parse_args()
    on = load_config(args.config).segmentation
    on = dataclasses.replace(on, photometric=True)
    off = dataclasses.replace(on, photometric=False)
    scenes = []
    for subject in load_dataset(args.data):
        size = subject.camera.image_size
        frames, _ = load_frames(subject.background, size=size)
        images, _ = load_frames(subject.poses, size=size)
        model = fit_background(frames, on)
        scenes.append((model, images, segment(images, model, off).masks))
    print(
        f"{len(scenes)} subjects x 6 postures, {args.config.name}; F against the unchanged images"
    )
    print(
        "gains applied        photometric on: F min / mean   off: F min / mean   "
        "gains estimated (mean)   effect   implausible on / off"
    )
    for gains in [(1.0, 1.0, 1.0), *CHANGES]:
        g = torch.tensor(gains).view(1, 3, 1, 1)
        f_on, f_off, est, effect, bad_on, bad_off = [], [], [], [], 0, 0
        for model, images, reference in scenes:
            x = ((images * g).clamp(0, 1) * 255).round() / 255
            res_on, res_off = segment(x, model, on), segment(x, model, off)
            _, photo = match_background(x, model, on.threshold)
            f_on += [f_measure(res_on.masks[j], reference[j]) for j in range(len(x))]
            f_off += [f_measure(res_off.masks[j], reference[j]) for j in range(len(x))]
            est.append(photo.gains.mean(0))
            effect += photo.effect.tolist()
            bad_on += sum(r is not None for r in implausible(res_on.masks, on.plausibility))
            bad_off += sum(r is not None for r in implausible(res_off.masks, on.plausibility))
        mean_gain = torch.stack(est).mean(0).tolist()
        label = "/".join(f"{v:.2f}" for v in gains)
        print(
            f"{label:16s}  {min(f_on):14.4f} / {statistics.mean(f_on):.4f}"
            f"  {min(f_off):11.4f} / {statistics.mean(f_off):.4f}   "
            f"{'/'.join(f'{v:.4f}' for v in mean_gain):22s}  {statistics.mean(effect):6.3f}   "
            f"{bad_on:2d} / {bad_off:2d} of {len(f_on)}"
        )


if __name__ == "__main__":
    main()
