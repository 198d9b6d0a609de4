"""Tracking speed: one sequence against B sequences advanced together (one frame per row).

    python benchmarks/bench_track.py --model RUN/SUBJECT --sequence SEQ_DIR \
        [--frames 8] [--batch 16] [--repeats 3] [--baseline jacobian=batched,ftol=1e-8,xtol=1e-8]

The B rows are the same sequence (the per-row work is the same, so the ratio is the batching's
gain alone). Silhouettes are segmented once beforehand and timed separately (per image); the
tracker's time per frame per sequence is measured for B = 1 and B = ``--batch``, interleaved
``--repeats`` times (medians quoted), as wall time and as this process's CPU time (the latter
holds better on a shared machine). The first frame (its start hypotheses) is not timed.
``--contour-workers N`` spreads the contour choice over N processes (started during the
untimed first frame). ``--baseline`` also times the tracker with those options changed
(``configs/track.yaml``'s ``track:`` keys), interleaved with the defaults in the same process.
``--prepared`` hands the tracker each frame's contours and distance maps made beforehand (timed
separately, per image), as ``tools/track.py`` does in its reader process, instead of the
silhouettes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time

import torch
import yaml

from torchfit.body.model import BodyModel
from torchfit.camera import stack_cameras
from torchfit.fit.contour_pool import set_contour_workers
from torchfit.image import fit_background, segment
from torchfit.io.images import load_frames
from torchfit.pipeline.track import TrackConfig, load_fitted, load_sequence
from torchfit.track import PoseLayout, frame_data, start_poses, track


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True)
    p.add_argument("--sequence", required=True)
    p.add_argument("--frames", type=int, default=8)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--baseline", default=None, help="KEY=VALUE,... tracker options to compare")
    p.add_argument(
        "--prepared", action="store_true", help="frames as contours and distance maps (see above)"
    )
    p.add_argument(
        "--contour-workers",
        type=int,
        default=0,
        help="processes sharing the contour choice (torchfit.fit.contour_pool); the CPU times "
        "are this process's alone",
    )
    args = p.parse_args()
    set_contour_workers(args.contour_workers)
    cfg = TrackConfig()
    variants = {"defaults": cfg.track}
    if args.baseline:
        fields = {f.name for f in dataclasses.fields(cfg.track)}
        changes = {}
        for item in args.baseline.split(","):
            key, value = item.split("=", 1)
            if key not in fields:
                p.error(f"--baseline: unknown tracker option {key!r}")
            parsed = yaml.safe_load(value)  # numbers, null, strings
            default = getattr(cfg.track, key)
            changes[key] = float(parsed) if isinstance(default, float) else parsed
        variants["baseline"] = dataclasses.replace(cfg.track, **changes)
    template, scales, _, _ = load_fitted(args.model)
    model = BodyModel(template)
    sc = torch.tensor([scales[s] for s in model.template.segments], dtype=torch.float64)
    seq = load_sequence(args.sequence, args.frames + 1)
    bg, _ = load_frames(seq.background, seq.camera.image_size)
    background = fit_background(bg, cfg.segmentation)
    t0 = time.perf_counter()
    masks = []
    for path in seq.frames:
        image, _ = load_frames([path], seq.camera.image_size)
        masks.append(segment(image, background, cfg.segmentation).masks[0, 0])
    seg_ms = 1000 * (time.perf_counter() - t0) / len(seq.frames)
    layout = PoseLayout(model, cfg.track)
    cam1 = seq.camera.to(dtype=model.dtype)
    x0 = start_poses(model, sc[None], cam1, masks[0][None], layout, cfg.track)
    sizes = (1, args.batch)
    prepared, prep_ms = {}, None
    if args.prepared:
        t0 = time.perf_counter()
        for b in sizes:
            cams = stack_cameras([seq.camera] * b).to(dtype=model.dtype)
            prepared[b] = [
                frame_data(m[None].expand(b, -1, -1), cams, cfg.track, model.dtype)
                for m in masks[1:]
            ]
        prep_ms = 1000 * (time.perf_counter() - t0) / (len(masks[1:]) * sum(sizes))
    wall = {(v, b): [] for v in variants for b in sizes}
    cpu = {(v, b): [] for v in variants for b in sizes}
    for _ in range(args.repeats):
        for name, options in variants.items():
            for b in sizes:
                cams = stack_cameras([seq.camera] * b).to(dtype=model.dtype)
                frames = prepared[b] if prepared else (m[None].expand(b, -1, -1) for m in masks[1:])
                t0, c0 = time.perf_counter(), time.process_time()
                track(
                    model,
                    sc[None].expand(b, -1, -1).contiguous(),
                    cams,
                    frames,
                    x0.expand(b, -1),
                    options,
                )
                wall[name, b].append(1000 * (time.perf_counter() - t0) / (args.frames * b))
                cpu[name, b].append(1000 * (time.process_time() - c0) / (args.frames * b))
    report = {
        "segmentation_ms_per_image": round(seg_ms, 1),
        "threads": torch.get_num_threads(),
        "contour_workers": args.contour_workers,
    }
    if prep_ms is not None:
        report["contours_and_distance_maps_ms_per_image"] = round(prep_ms, 1)
    for name in variants:
        one = statistics.median(wall[name, 1])
        many = statistics.median(wall[name, args.batch])
        report[name] = {
            "track_ms_per_frame_B1": round(one, 1),
            f"track_ms_per_frame_per_sequence_B{args.batch}": round(many, 1),
            "fps_ratio": round(one / many, 2),
            "cpu_ms_per_frame_B1": round(statistics.median(cpu[name, 1]), 1),
            f"cpu_ms_per_frame_per_sequence_B{args.batch}": round(
                statistics.median(cpu[name, args.batch]), 1
            ),
            "runs_ms": {str(b): [round(v, 1) for v in wall[name, b]] for b in sizes},
        }
    if "baseline" in variants:
        report["speed_up_B1"] = round(
            statistics.median(wall["baseline", 1]) / statistics.median(wall["defaults", 1]), 2
        )
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
