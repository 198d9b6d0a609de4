"""Speed of the segmentation chain and of the chamfer transform on this machine's CPU.

    python benchmarks/bench_segmentation.py [--batch 1 8 16] [--repeats 7] [--threads N]
        [--modes eager compiled]

Prints machine and versions, then

1. frames per second at 720x576 for the whole chain, batched: photometric compensation
   (per-channel gains against the background, ``segmentation.photometric``; off with
   ``--no-photometric``), Mahalanobis test (HSL), the shadow test of the default options
   (attenuation, chromaticity, texture; its own column), clean-up (opening, largest region,
   closing, hole filling; with ``segmentation.edge_width`` the outline's mixed pixels), ordered
   outer contour, contour mask and 3-4 chamfer distance map; with the time of each stage;
   the colour test eager and through ``torch.compile`` (``segmentation.compile: true``;
   compile time printed apart);
2. the torch 3-4 chamfer transform against ``cv2.distanceTransform(DIST_L2, 3)`` on the same
   contour images (both per image), and the exact Euclidean option.

Every figure is the median of ``--repeats`` runs after one warm-up run. The scene is synthetic
(a textured background, a person-like silhouette with a cast shadow, sensor noise), so that
the figures do not depend on data that may be absent; F-measures on real footage are printed
by ``benchmarks/eval_segmentation.py``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import cv2
import kornia
import numpy as np
import torch

from torchfit.image import (
    SegmentationOptions,
    cast_shadow,
    chamfer_distance_transform,
    clean_mask,
    contour_mask,
    distance_map,
    euclidean_distance_transform,
    fit_background,
    implausible,
    mahalanobis_distance,
    match_background,
    outer_contours,
    refine_edges,
)

W, H = 720, 576


def machine() -> str:
    cpu = platform.processor() or "?"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    load = os.getloadavg() if hasattr(os, "getloadavg") else ("?",)
    return (
        f"{platform.platform()} | {cpu} | {os.cpu_count()} logical CPUs | "
        f"load average {load[0]:.2f} | torch {torch.__version__} "
        f"({torch.get_num_threads()} threads) | kornia {kornia.__version__} | "
        f"opencv {cv2.__version__} | numpy {np.__version__}"
    )


#: the clock of every timing: wall time, or with --cpu-time the process's CPU time
CLOCK = {"clock": time.perf_counter}


def median_time(fn, repeats: int) -> float:
    clock = CLOCK["clock"]
    fn()
    times = []
    for _ in range(repeats):
        t0 = clock()
        fn()
        times.append(clock() - t0)
    return statistics.median(times)


def scene(batch: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """10 background frames ``(10, 3, H, W)`` and ``batch`` images with a person."""
    coarse = torch.rand(1, 3, 12, 15, generator=gen)
    bg = torch.nn.functional.interpolate(coarse, size=(H, W), mode="bilinear") * 0.5 + 0.2
    frames = (bg + torch.randn(10, 3, H, W, generator=gen) * 2 / 255).clamp(0, 1)
    person = np.zeros((H, W), np.uint8)
    cv2.ellipse(person, (360, 300), (70, 200), 0, 0, 360, 1, -1)  # body
    cv2.circle(person, (360, 80), 35, 1, -1)  # head
    cv2.line(person, (300, 200), (180, 330), 1, 25)  # arm
    shadow = np.zeros((H, W), np.uint8)
    cv2.ellipse(shadow, (480, 500), (140, 25), 0, 0, 360, 1, -1)
    img = bg.clone()
    img[:, :, torch.from_numpy(shadow).bool()] *= 0.6
    img[:, :, torch.from_numpy(person).bool()] = torch.tensor([0.8, 0.3, 0.2]).view(1, 3, 1)
    images = (img + torch.randn(batch, 3, H, W, generator=gen) * 2 / 255).clamp(0, 1)
    return frames, images


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--batch", type=int, nargs="+", default=[1, 8, 16])
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    p.add_argument(
        "--modes",
        nargs="+",
        choices=("eager", "compiled"),
        default=["eager", "compiled"],
        help="colour test eager and/or through torch.compile (segmentation.compile)",
    )
    p.add_argument(
        "--no-photometric",
        action="store_true",
        help="leave out the photometric compensation (segmentation.photometric: false)",
    )
    p.add_argument(
        "--cpu-time",
        action="store_true",
        help="time with the process's CPU time instead of wall time (on a shared machine; "
        "with --threads 1 it is the wall time a quiet machine would give)",
    )
    args = p.parse_args()
    if args.cpu_time:
        CLOCK["clock"] = time.process_time
    if args.threads:
        torch.set_num_threads(args.threads)
    print(machine())
    gen = torch.Generator().manual_seed(0)
    cfg = SegmentationOptions(photometric=not args.no_photometric)

    clock = CLOCK["clock"]
    unit = "CPU time" if args.cpu_time else "wall time"
    print(f"\n1. whole chain at {W}x{H}, CPU, {unit}, median of {args.repeats}")
    print(f"   photometric compensation: {'on' if cfg.photometric else 'off'}")
    print(
        "   'frames/s' is the whole row; 'seg f/s' the segmentation chain alone (photometric "
        "compensation,\n   colour test, shadow test, clean-up: what tools/segment.py runs per "
        "frame)"
    )
    print(
        "   colour test  batch  frames/s  seg f/s  ms/frame | photo  test  shadow  clean-up  "
        "contour  dist-map   (ms/frame)"
    )
    contours_for_dt = None
    for mode, b in [(m, b) for m in args.modes for b in args.batch]:
        frames, images = scene(b, gen)
        model = fit_background(frames, cfg)
        stages = {}
        compiled = mode == "compiled"
        if compiled:  # compile outside the timing (torch caches the kernel on disk)
            t0 = time.perf_counter()
            mahalanobis_distance(model, images, compiled=True)
            print(f"   (compiling for batch {b}: {time.perf_counter() - t0:.1f} s)")

        def chain(stages=stages, model=model, images=images, compiled=compiled):
            tp = clock()
            matched = match_background(images, model)[0] if cfg.photometric else images
            t0 = clock()
            raw = mahalanobis_distance(model, matched, compiled=compiled) > cfg.threshold
            t1 = clock()
            raw = raw & ~cast_shadow(model, matched, raw, cfg)
            ts = clock()
            masks = clean_mask(raw, cfg.open_kernel, cfg.close_kernel, cfg.fill_holes)
            if cfg.edge_width > 0:
                masks = refine_edges(matched, model, masks, cfg.edge_width, cfg.edge_separation)
            implausible(masks, cfg.plausibility)
            t2 = clock()
            pts = outer_contours(masks)
            seeds = torch.zeros_like(masks)
            for i, c in enumerate(pts):
                seeds[i, 0, c[:, 1], c[:, 0]] = True
            t3 = clock()
            dist = distance_map(seeds, cfg.distance)
            t4 = clock()
            for k, v in zip(
                ("photo", "test", "shadow", "clean", "contour", "dist"),
                (t0 - tp, t1 - t0, ts - t1, t2 - ts, t3 - t2, t4 - t3),
                strict=True,
            ):
                stages.setdefault(k, []).append(v)
            return dist

        total = median_time(chain, args.repeats)
        per = {k: statistics.median(v[1:]) / b * 1e3 for k, v in stages.items()}
        seg = statistics.median(
            sum(stages[k][i] for k in ("photo", "test", "shadow", "clean"))
            for i in range(1, len(stages["photo"]))
        )
        print(
            f"   {mode:11s}  {b:5d}  {b / total:8.1f}  {b / seg:7.1f}  {total / b * 1e3:8.1f} | "
            f"{per['photo']:5.1f}  {per['test']:5.1f}  {per['shadow']:6.1f}  "
            f"{per['clean']:8.1f}  {per['contour']:7.1f}  {per['dist']:8.1f}"
        )
        contours_for_dt = contour_mask(
            clean_mask(mahalanobis_distance(model, images) > cfg.threshold)
        )

    print(
        f"\n2. distance transform of the contour image at {W}x{H}, ms per image, "
        f"median of {args.repeats}"
    )
    seeds1 = contours_for_dt[:1]
    src = (~seeds1[0, 0].numpy()).astype(np.uint8)  # OpenCV measures to the zero pixels
    t_cv = median_time(lambda: cv2.distanceTransform(src, cv2.DIST_L2, 3), args.repeats) * 1e3
    print(f"   cv2.distanceTransform(DIST_L2, 3):           {t_cv:8.2f}")
    for b in args.batch:
        seeds = seeds1.expand(b, -1, -1, -1).contiguous()
        for algo in ("rows", "lines"):
            t = median_time(lambda s=seeds, a=algo: chamfer_distance_transform(s, a), args.repeats)
            t = t / b * 1e3
            print(
                f"   torch chamfer 3-4 '{algo}', batch {b:3d}:     {t:8.2f}   "
                f"({t / t_cv:5.2f}x OpenCV)"
            )
    t_e = median_time(lambda: euclidean_distance_transform(seeds1), max(3, args.repeats // 2)) * 1e3
    print(f"   torch exact Euclidean, batch   1:          {t_e:8.2f}   ({t_e / t_cv:5.2f}x OpenCV)")


if __name__ == "__main__":
    main()
