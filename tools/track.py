"""Motion capture with a fitted model: track the person's silhouette in one or more sequences.

    python tools/track.py --config configs/track.yaml --model RUN_DIR/SUBJECT \
        --sequence SEQ_DIR [--sequence SEQ_DIR2 ...] --out OUT_DIR [--frames N]

``--model`` is a fitted subject folder (its ``params.json`` gives the template and the segment
scales, which stay fixed). Each ``SEQ_DIR`` holds ``camera.yaml``, ``background/*.png``,
``frames/000000.png`` … (or ``--video FILE``, one per sequence) and optionally ``masks/`` (your
own silhouettes, one per frame: ``segmentation.method`` ``auto`` or ``masks``; no
``background/`` needed then) and ``truth.json``. ``segmentation.method: chroma_key`` keys a
coloured screen instead (``segmentation.chroma_key``).
Several sequences are tracked together, one frame per batch row. Writes per sequence
``OUT_DIR/<k>_<name>/`` (``OUT_DIR`` itself for a single sequence): ``joints_world.json``,
``motion.bvh``, ``track.csv``, ``overlay/`` and ``overlay.avi`` with ``--overlays`` and, with
a truth, ``eval.json``; TensorBoard scalars in ``OUT_DIR/tb``.

Exit codes: 0 ok, 1 a sequence lost frames (status ``uncertain``), 2 bad arguments or config
(also a chroma key with neither ``segmentation.chroma_key.key`` nor background frames), 3 output
not writable, 4 model or sequence missing or unreadable (also a frame or mask found unreadable
or of another size while tracking, too few background frames, or a chroma key's background
frames that show no screen). A sequence found unreadable while tracking is named and left out:
the others are tracked again without it (as they would be alone) and written, and the exit
code is 4.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

from torchfit.config import load_config  # noqa: E402
from torchfit.errors import (  # noqa: E402
    ConfigError,
    DataError,
    OutputError,
    SegmentationError,
    SequenceError,
    TorchfitError,
)

#: a sequence whose median frame confidence is below this (a contour RMS above
#: ``track.confidence_px`` in most frames) gets a warning: on the thirty development clips the
#: three below it are tracked at 162-359 mm (mean 234), the other 27 at 38-263 (mean 114)
DOUBTFUL_CONFIDENCE = 0.5


def _cpu_seconds() -> float:
    """CPU time of this process and of its finished children (the frame reader's)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=None, help="YAML file (configs/track.yaml)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--model", required=True, help="fitted subject folder (params.json)")
    parser.add_argument("--sequence", action="append", required=True, help="sequence folder")
    parser.add_argument(
        "--video",
        action="append",
        default=None,
        help="read a sequence's frames from this video instead of its frames/ (one per "
        "--sequence, in order)",
    )
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--frames", type=int, default=None, help="track only the first N frames")
    parser.add_argument(
        "--true-skeleton",
        default=None,
        metavar="SUBJECT_DIR",
        help="a synthetic subject folder: replace the fitted segment lengths by its true ones "
        "(truth.json), to measure the tracker alone",
    )
    parser.add_argument(
        "--overlays", action="store_true", help="write overlay/<frame>.png and overlay.avi"
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch CPU threads (default: one fewer than the cores, at least 1: the remaining "
        "core reads and segments the next frames meanwhile)",
    )
    parser.add_argument(
        "--ahead",
        choices=("process", "thread", "none"),
        default=None,
        help="where the next frames are read, segmented and turned into contours and distance "
        "maps while one is tracked (default: a second process where there are two cores or "
        "more, else none)",
    )
    parser.add_argument(
        "--readers",
        type=int,
        default=None,
        help="processes that read and segment the frames, each for a group of the sequences "
        "(default: with several sequences and --ahead process or thread, as many as the cores, "
        "at most one a sequence; else 1). The tracks are the same for any number",
    )
    args = parser.parse_args(argv)
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")
    if args.frames is not None and args.frames < 1:
        parser.error(f"--frames must be >= 1, got {args.frames}")
    if args.readers is not None and args.readers < 1:
        parser.error(f"--readers must be >= 1, got {args.readers}")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from torchfit.pipeline.runtime import cpu_count

    torch.set_num_threads(args.threads or max(1, cpu_count() - 1))
    ahead = args.ahead or ("process" if cpu_count() > 1 else "none")
    from torchfit.body.model import BodyModel
    from torchfit.pipeline.tensorboard import TensorBoardCallback
    from torchfit.pipeline.track import (
        TrackConfig,
        load_fitted,
        load_sequence,
        skeleton_scales,
    )

    try:
        config = load_config(args.config, args.set, schema=TrackConfig)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        template, scales, status, why = load_fitted(args.model)
        if status != "ok":
            print(
                f"warning: {args.model} is {status} ({why}); its segment lengths may be wrong, "
                "and so may the tracked joints",
                file=sys.stderr,
            )
        model = BodyModel(template)
        if args.true_skeleton:
            truth = json.loads((Path(args.true_skeleton) / "truth.json").read_text())
            scales = skeleton_scales(model, scales, truth["joints_world"]["pose1"])
        order = model.template.segments
        scale_t = torch.tensor([scales[s] for s in order], dtype=torch.float64)
        videos = args.video or [None] * len(args.sequence)
        if len(videos) != len(args.sequence):
            print("error: give one --video per --sequence", file=sys.stderr)
            return 2
        seqs = [
            load_sequence(s, args.frames, v, config.segmentation.method)
            for s, v in zip(args.sequence, videos, strict=True)
        ]
    except (DataError, KeyError, OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 4
    out = Path(args.out)
    outs = [out] if len(seqs) == 1 else [out / f"{k:02d}_{s.name}" for k, s in enumerate(seqs)]
    live = list(range(len(seqs)))  # the sequences tracked; one that fails is left out
    failed: dict[int, str] = {}
    summaries: list[dict] = []
    try:
        out.mkdir(parents=True, exist_ok=True)
        t0, c0 = time.perf_counter(), _cpu_seconds()
        with TensorBoardCallback(out / "tb", "track") as tb:
            while live:
                try:
                    summaries = _track(args, config, model, scale_t, seqs, outs, live, tb, ahead)
                    break
                except SequenceError as exc:
                    # nothing was written yet: the others are tracked again without it,
                    # as they would be alone
                    k = live.pop(exc.index)
                    failed[k] = str(exc)
                    print(f"error: {seqs[k].name} ({args.sequence[k]}): {exc}", file=sys.stderr)
        wall, cpu = time.perf_counter() - t0, _cpu_seconds() - c0
    except OutputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    except OSError as exc:
        print(f"error: cannot write {out}: {exc}", file=sys.stderr)
        return 3
    except (DataError, SegmentationError) as exc:  # a frame, mask or background image that
        # cannot be used, not a single sequence's (the start of the first frames)
        print(f"error: {exc}", file=sys.stderr)
        return 4
    except ConfigError as exc:  # a chroma key with neither a key colour nor background frames
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    for s in summaries:
        if s["median_confidence"] < DOUBTFUL_CONFIDENCE:
            print(
                f"warning: {s['sequence']}: median confidence {s['median_confidence']:.2f}: the "
                "model explains its silhouettes poorly (a contour RMS above track.confidence_px "
                "in most frames), so its joints are likely off; check the overlays (light "
                "clothes before a light background can lose the legs to the shadow test)",
                file=sys.stderr,
            )
    frames = sum(s["frames"] for s in summaries)
    report = {
        "model_status": status,
        "wall_s": round(wall, 2),
        "cpu_s": round(cpu, 2),
        "frames": frames,
        "fps": round(frames / wall, 2),
        "sequences": [
            {k: v for k, v in s.items() if k not in ("per_frame_mm",)} for s in summaries
        ],
        "failed": [{"sequence": args.sequence[k], "error": e} for k, e in failed.items()],
    }
    print(json.dumps(report, indent=1))
    if failed:
        return 4
    return 1 if any(s["status"]["uncertain"] for s in summaries) else 0


def _track(args, config, model, scales, seqs, outs, live, tb, ahead) -> list[dict]:
    """:func:`track_sequences` of the sequences ``live`` (positions in ``seqs``)."""
    from torchfit.pipeline.runtime import cpu_count
    from torchfit.pipeline.track import track_sequences

    chosen = [seqs[k] for k in live]
    total = max(s.num_frames for s in chosen)
    return track_sequences(
        model,
        scales,
        chosen,
        [outs[k] for k in live],
        config,
        tb,
        progress=lambda it: tqdm(it, desc="frames", total=total),
        overlays=args.overlays,
        ahead=ahead,
        readers=args.readers or (1 if ahead == "none" else min(len(chosen), cpu_count())),
    )


if __name__ == "__main__":
    sys.exit(main())
