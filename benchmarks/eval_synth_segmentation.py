"""Segmentation quality on synthetic subjects, against the renderer's true masks.

    python benchmarks/eval_synth_segmentation.py --data DIR [--config FILE] [--set k=v]
        [--subjects subject_000 ...] [--stereo] [--overlays OUT] [--csv FILE] [--quiet]

``DIR`` holds subject folders written by ``tools/make_subjects.py`` with their evaluation
masks (``truth_masks/poseK.png`` and ``truth_masks/poseK_shadow.png``; add them to older
subjects with ``--masks-only``). ``--config`` is a full run config (its ``segmentation``
section is used; default: the library's ``SegmentationOptions()``); ``--set`` overrides take
``segmentation.KEY=VALUE`` or just ``KEY=VALUE``. ``--global-gain`` divides each posture
image by its per-channel median ratio to the background mean before segmenting (a crude
stand-in for photometric compensation, for rooms whose exposure changes between the
background frames and the postures).

Per subject and posture image it prints:

- ``P``, ``R``, ``F``: precision, recall and F-measure of the cleaned mask against the true
  person silhouette (pixels);
- ``shadow_bg``: the share of the true cast-shadow pixels (outside the person) that the mask
  keeps as background (``-`` when the image has none);
- ``cd``: the mean distance in pixels between the predicted and the true **outer** contours
  (what the fit sees, :func:`torchfit.image.contour_mask`), symmetric: the mean of
  "predicted contour pixel to nearest true contour pixel" and the reverse, each from an exact
  Euclidean distance transform; ``cd_max`` the 95th percentile of both directions.

Then the means over all images and per posture, and the figures pooled over the pixels of
all images (``pooled``: F from the summed counts, and the share of all cast-shadow pixels
kept as background), the figures to compare between datasets (standard and hard rooms,
``configs/synth_hard.yaml``). ``--csv FILE`` writes the per-image rows. ``--overlays OUT``
writes, per image, a PNG with true positives grey, false positives (the mask where the
person is not) red, false negatives (person missed) blue, and the true shadow outlined in
yellow.
"""

from __future__ import annotations

import argparse
import csv
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from torchfit.config import Config, config_to_dict, load_config
from torchfit.image import contour_mask, fit_background, segment
from torchfit.io import load_frames, read_mask


def _contour_distance(pred: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Symmetric mean and 95th percentile distance (px) between the outer contours."""
    masks = torch.from_numpy(np.stack([pred, truth]))[:, None]
    cp, ct = (c[0].numpy() for c in contour_mask(masks))
    if not cp.any() or not ct.any():
        return float("inf"), float("inf")
    # distance to the nearest contour pixel: transform of the complement of the contour
    dt_t = cv2.distanceTransform((~ct).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    dt_p = cv2.distanceTransform((~cp).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    a, b = dt_t[cp], dt_p[ct]
    both = np.concatenate([a, b])
    return 0.5 * (float(a.mean()) + float(b.mean())), float(np.percentile(both, 95))


def _overlay(image: np.ndarray, pred: np.ndarray, truth: np.ndarray, shadow: np.ndarray):
    """(H, W, 3) uint8 BGR overlay for eyeballing."""
    out = (image[..., ::-1].astype(np.float32) * 0.6).astype(np.uint8)
    out[pred & truth] = (out[pred & truth] * 0.4 + 150).astype(np.uint8)
    out[pred & ~truth] = (0, 0, 255)
    out[~pred & truth] = (255, 80, 0)
    edges = cv2.morphologyEx(shadow.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3)))
    out[edges > 0] = (0, 255, 255)
    return out


def _global_gain(frames: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Each image divided by its per-channel median ratio to the background mean: a crude
    stand-in for photometric compensation (exposure, white balance), so that the shadow test
    can be scored apart from exposure changes."""
    mean = background.mean(0, keepdim=True)
    gain = (frames / mean.clamp_min(0.02)).flatten(2).median(2).values[..., None, None]
    return (frames / gain).clamp(0, 1)


def evaluate_subject(
    folder: Path, cfg, stereo: bool, overlays: Path | None, gain: bool = False
) -> list[dict]:
    """Rows of figures for the posture images (and the stereo pair) of one subject."""
    views = [(folder / "background", [folder / "poses" / f"pose{k}.png" for k in range(1, 7)])]
    truth_dirs = [folder / "truth_masks"]
    if stereo and (folder / "stereo" / "truth_masks").is_dir():
        for side in ("left", "right"):
            views.append(
                (folder / "stereo" / "background" / side, [folder / "stereo" / f"{side}.png"])
            )
            truth_dirs.append(folder / "stereo" / "truth_masks")
    rows = []
    for (bg_dir, images), tdir in zip(views, truth_dirs, strict=True):
        bg, _ = load_frames(bg_dir)
        model = fit_background(bg, cfg)
        frames, paths = load_frames(images)
        if gain:
            frames = _global_gain(frames, bg)
        res = segment(frames, model, cfg)
        for i, path in enumerate(paths):
            pred = res.masks[i, 0].numpy()
            truth = read_mask(tdir / f"{path.stem}.png") > 0
            shadow = read_mask(tdir / f"{path.stem}_shadow.png") > 0
            tp = int((pred & truth).sum())
            fp = int((pred & ~truth).sum())
            fn = int((~pred & truth).sum())
            p = tp / (tp + fp) if tp + fp else 0.0
            r = tp / (tp + fn) if tp + fn else 0.0
            f = 2 * p * r / (p + r) if p + r else 0.0
            n_sh = int(shadow.sum())
            sh_bg = float((~pred & shadow).sum() / n_sh) if n_sh else float("nan")
            cd, cd95 = _contour_distance(pred, truth)
            name = path.stem if tdir.parent == folder else f"stereo_{path.stem}"
            rows.append(
                {
                    "subject": folder.name,
                    "image": name,
                    "P": p,
                    "R": r,
                    "F": f,
                    "shadow_bg": sh_bg,
                    "cd": cd,
                    "cd95": cd95,
                    "tp": tp,
                    "fp": fp,
                    "fn": fn,
                    "shadow": n_sh,
                    "shadow_kept": int((~pred & shadow).sum()),
                }
            )
            if overlays is not None:
                img = (frames[i].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
                overlays.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(
                    str(overlays / f"{folder.name}_{name}.png"), _overlay(img, pred, truth, shadow)
                )
    return rows


def _mean(rows: list[dict], key: str) -> float:
    vals = np.array([r[key] for r in rows], dtype=float)
    vals = vals[np.isfinite(vals)]
    return float(vals.mean()) if vals.size else float("nan")


def _fmt(x: float) -> str:
    return "    -" if not np.isfinite(x) else f"{x:5.3f}" if x <= 1.0 else f"{x:5.2f}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="dataset folder with truth masks")
    parser.add_argument("--config", default=None, help="run config YAML (segmentation section)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--subjects", nargs="*", default=None)
    parser.add_argument("--stereo", action="store_true", help="also score the stereo pair")
    parser.add_argument("--overlays", default=None, help="write overlay PNGs to this folder")
    parser.add_argument("--csv", default=None, help="write the per-image rows to this CSV")
    parser.add_argument("--quiet", action="store_true", help="print only the means")
    parser.add_argument(
        "--global-gain",
        action="store_true",
        help="divide each image by its per-channel median ratio to the background first",
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    overrides = [s if s.startswith("segmentation.") else f"segmentation.{s}" for s in args.set]
    cfg = load_config(args.config, overrides, schema=Config).segmentation
    root = Path(args.data)
    folders = sorted(p for p in root.iterdir() if (p / "truth_masks").is_dir())
    if args.subjects:
        folders = [p for p in folders if p.name in args.subjects]
    if not folders:
        sys.exit(f"no subject with truth_masks/ in {root} (make_subjects.py --masks-only)")
    print(f"# {root}  {len(folders)} subjects  python {platform.python_version()}")
    print(f"# torch {torch.__version__}, opencv {cv2.__version__}")
    print("# segmentation:", config_to_dict(cfg))
    start = time.perf_counter()
    rows: list[dict] = []
    overlays = Path(args.overlays) if args.overlays else None
    header = f"{'subject':12s} {'image':13s}     P     R     F shadow_bg    cd  cd95"
    if not args.quiet:
        print(header)
    for folder in folders:
        new = evaluate_subject(folder, cfg, args.stereo, overlays, args.global_gain)
        rows += new
        if not args.quiet:
            for r in new:
                print(
                    f"{r['subject']:12s} {r['image']:13s} {_fmt(r['P'])} {_fmt(r['R'])} "
                    f"{_fmt(r['F'])}     {_fmt(r['shadow_bg'])} {_fmt(r['cd'])} {_fmt(r['cd95'])}"
                )
    print(f"# {len(rows)} images, {time.perf_counter() - start:.0f} s")
    print(f"{'mean per image':26s}     P     R     F shadow_bg    cd  cd95")
    groups = [("all", rows)] + [
        (name, [r for r in rows if r["image"] == name])
        for name in sorted({r["image"] for r in rows})
    ]
    for name, group in groups:
        print(
            f"{name:26s} {_fmt(_mean(group, 'P'))} {_fmt(_mean(group, 'R'))} "
            f"{_fmt(_mean(group, 'F'))}     {_fmt(_mean(group, 'shadow_bg'))} "
            f"{_fmt(_mean(group, 'cd'))} {_fmt(_mean(group, 'cd95'))}"
        )
    tp, fp, fn = (sum(r[k] for r in rows) for k in ("tp", "fp", "fn"))
    p, r = tp / max(tp + fp, 1), tp / max(tp + fn, 1)
    n_sh = sum(r["shadow"] for r in rows)
    kept = sum(r["shadow_kept"] for r in rows) / n_sh if n_sh else float("nan")
    print(
        f"{'pooled':26s} {_fmt(p)} {_fmt(r)} {_fmt(2 * p * r / max(p + r, 1e-12))}     "
        f"{_fmt(kept)}   (cast-shadow pixels: {n_sh})"
    )
    if args.csv:
        with open(args.csv, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    worst = sorted(rows, key=lambda r: -r["cd"])[:5]
    print("worst cd:", ", ".join(f"{r['subject']}/{r['image']} {r['cd']:.1f}" for r in worst))


if __name__ == "__main__":
    main()
