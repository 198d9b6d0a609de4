"""Guided capture: from a video of the six postures to a subject folder.

    python tools/capture.py --video FILE_OR_FRAME_FOLDER --camera camera.yaml --out SUBJECT_DIR \
        [--height-m H] [--hold-frames N] [--min-score S] [--config FILE] [--set key=value]

The video (a video file OpenCV can read, or a folder of frames sorted by name) starts with the
empty scene; the person then walks onto the floor mark and strikes the six postures of
design.md section 4 in order, holding each still for about a second. The tool takes the
background frames from the empty start, segments the later frames, finds the still stretches
and, for each posture in order, picks the frame whose silhouette best matches the posture's
template silhouette projected with the camera (scaled to ``--height-m``, or to the
silhouette's height) (torchfit.capture.offline). A held posture's image is the per-pixel
median of up to ``--hold-frames`` frames around the chosen one (contiguous, inside its still
stretch, each silhouette overlapping the chosen frame's with an intersection over union of at
least ``--hold-iou``), which removes most of one frame's sensor noise; ``--hold-frames 1``
(the default) writes the chosen frame itself. On the development subjects the median did not
bring the fit closer to the original images (benchmarks/RESULTS.md, Calibration and capture).

Writes ``SUBJECT_DIR/background/bg01.png`` …, ``poses/pose1.png`` … ``pose6.png``, a copy of
``camera.yaml`` and ``capture.json`` (the background frames, the chosen frame, the frames
combined and the match score per posture, the still stretches). A posture not found is named
in an error; the postures found are still written. Only the ``segmentation:`` section of
``--config`` is used.

Live (``--device 0``, or a video file standing in for the camera): the guidance of the first
paper's section 9 as a web page on the loopback interface only, ``http://127.0.0.1:PORT``
(``--port``, default 8765; the address is printed): the live image with the target posture's
template contour and the match score. Step out of view for the first 10 frames (the
background); a posture is captured when its score stays at least ``--min-score`` (0.5) for
a second, then the next one is the target; its image is the median of the last frames of
that second (up to ``--hold-frames``) whose silhouettes agree with the last one's.

Exit codes: 0 all six postures captured; 1 some posture not found (the others written);
2 bad arguments or config; 3 the outputs cannot be written; 4 the video or camera missing or
unreadable, or too few empty frames at its start.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

from torchfit.capture.offline import CaptureOptions  # noqa: E402
from torchfit.config import Config, load_config  # noqa: E402
from torchfit.errors import DataError, OutputError, TorchfitError  # noqa: E402
from torchfit.io.camera import load_camera, save_camera  # noqa: E402
from torchfit.io.files import write_atomic  # noqa: E402
from torchfit.io.images import list_images, read_image, write_image  # noqa: E402

#: the capture's defaults (``--hold-frames``, ``--hold-iou``, ``--min-score``)
DEFAULTS = CaptureOptions()
POSTURE_NAMES = ("stand", "straddle", "side_knee", "t_pose", "cactus", "side_stand")


def read_video(source: Path) -> tuple[torch.Tensor, float | None]:
    """(N, 3, H, W) uint8 RGB and the frame rate (None for a frame folder)."""
    if source.is_dir():
        paths = list_images(source)
        if not paths:
            raise DataError(f"no frames found in {source}")
        images = []
        for path in paths:
            image = read_image(path)
            if images and image.shape != images[0].shape:
                raise DataError(
                    f"frame {path}: {image.shape[1]}x{image.shape[0]} pixels, the first frame "
                    f"is {images[0].shape[1]}x{images[0].shape[0]}"
                )
            images.append(image)
        return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous(), None
    if not source.is_file():
        raise DataError(f"video not found: {source}")
    video = cv2.VideoCapture(str(source))
    fps = video.get(cv2.CAP_PROP_FPS) or None
    images = []
    while True:
        ok, bgr = video.read()
        if not ok:
            break
        images.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    video.release()
    if not images:
        raise DataError(f"{source}: not a video OpenCV can read (no frames decoded)")
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous(), fps


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--video", type=Path, help="video file or folder of frames")
    src.add_argument(
        "--device", help="live: an OpenCV camera number (0) or a video file standing in for one"
    )
    p.add_argument("--camera", required=True, type=Path, help="camera.yaml of the video")
    p.add_argument("--out", required=True, type=Path, help="the subject folder to write")
    p.add_argument("--height-m", type=float, help="the person's height, metres")
    p.add_argument(
        "--hold-frames",
        type=int,
        default=DEFAULTS.hold_frames,
        metavar="N",
        help="frames combined (per-pixel median) per posture image; 1: the chosen frame alone "
        f"(default {DEFAULTS.hold_frames})",
    )
    p.add_argument(
        "--hold-iou",
        type=float,
        default=DEFAULTS.hold_iou,
        help="a combined frame's silhouette overlap (IoU) with the chosen frame's, at least "
        f"(default {DEFAULTS.hold_iou})",
    )
    p.add_argument(
        "--min-score",
        type=float,
        default=DEFAULTS.min_score,
        help="a posture's frame must match its template with at least this intersection "
        f"over union (default {DEFAULTS.min_score})",
    )
    p.add_argument("--config", type=Path, help="torchfit config YAML (segmentation: section)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--port", type=int, default=8765, help="live: the page's port (0: any free)")
    p.add_argument(
        "--linger", type=float, default=0.0, help="live: keep serving this many seconds at the end"
    )
    args = p.parse_args(argv)
    if args.height_m is not None and not 0.5 < args.height_m < 2.8:
        p.error(f"--height-m must be a person's height in metres, got {args.height_m}")
    if args.hold_frames < 1:
        p.error(f"--hold-frames must be at least 1, got {args.hold_frames}")
    if not 0.0 < args.min_score < 1.0:
        p.error(f"--min-score must be in (0, 1), got {args.min_score}")
    if not 0.0 < args.hold_iou <= 1.0:
        p.error(f"--hold-iou must be in (0, 1], got {args.hold_iou}")
    return args


def _capture_options(args: argparse.Namespace) -> CaptureOptions:
    return CaptureOptions(
        min_score=args.min_score, hold_frames=args.hold_frames, hold_iou=args.hold_iou
    )


def _frame(frames: torch.Tensor, i: int) -> np.ndarray:
    return np.ascontiguousarray(frames[i].permute(1, 2, 0).numpy())


def live(args: argparse.Namespace, config: Config) -> int:
    """``--device``: the guidance page while capturing (torchfit.capture.live)."""
    from torchfit.body.model import BodyModel
    from torchfit.capture.live import GuidanceServer, run_live

    try:
        camera = load_camera(args.camera)
        model = BodyModel(config.model.template)
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 4
    source = int(args.device) if str(args.device).isdigit() else str(args.device)
    try:
        server = GuidanceServer(args.port)
    except OSError as exc:
        print(f"error: cannot serve on 127.0.0.1:{args.port}: {exc.strerror}", file=sys.stderr)
        return 2
    print(f"guidance at {server.url}", flush=True)
    try:
        captured = run_live(
            source,
            camera,
            model,
            args.out,
            server,
            args.height_m,
            config.segmentation,
            _capture_options(args),
        )
        time.sleep(max(args.linger, 0.0))
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 4
    except (OutputError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    finally:
        server.close()
    missing = [k for k in range(1, 7) if k not in captured]
    if missing:
        names = ", ".join(f"pose{k} ({POSTURE_NAMES[k - 1]})" for k in missing)
        print(f"error: not captured: {names}", file=sys.stderr)
        return 1
    print(f"wrote {args.out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        config = load_config(args.config, args.set, schema=Config)
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.device is not None:
        return live(args, config)
    try:
        camera = load_camera(args.camera)
        frames, fps = read_video(args.video)
        from torchfit.body.model import BodyModel
        from torchfit.capture.offline import capture_from_frames, median_frame

        model = BodyModel(config.model.template)
        result = capture_from_frames(
            frames,
            camera,
            model,
            args.height_m,
            config.segmentation,
            _capture_options(args),
            progress=lambda n: tqdm(total=n, desc="segment", unit="frame"),
        )
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 4
    document = {
        "video": str(args.video),
        "fps": fps,
        "frames": int(frames.shape[0]),
        "height_m": args.height_m,
        "hold_frames": args.hold_frames,
        "hold_iou": args.hold_iou,
        "background_frames": result.background,
        "still_stretches": [list(s) for s in result.stretches],
        "postures": {
            f"pose{k}": {
                "name": POSTURE_NAMES[k - 1],
                "frame": result.chosen.get(k),
                "combined_frames": result.combined.get(k),
                "score": round(result.scores.get(k, 0.0), 4),
                "frame_cut": result.cut.get(k),
            }
            for k in range(1, 7)
        },
    }
    try:
        for n, i in enumerate(result.background, start=1):
            write_image(args.out / "background" / f"bg{n:02d}.png", _frame(frames, i))
        for k, indices in result.combined.items():
            write_image(args.out / "poses" / f"pose{k}.png", median_frame(frames, indices))
        save_camera(camera, args.out / "camera.yaml")
        write_atomic(args.out / "capture.json", json.dumps(document, indent=1))
    except (OutputError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    for k in range(1, 7):
        entry = document["postures"][f"pose{k}"]
        used = entry["combined_frames"] or []
        where = f"frame {entry['frame']}" if entry["frame"] is not None else "NOT FOUND"
        if len(used) > 1:
            where += f" (median of {used[0]}-{used[-1]})"
        print(f"pose{k} ({entry['name']}): {where}, score {entry['score']:.3f}")
        if entry["frame_cut"]:
            print(
                f"warning: pose{k} ({entry['name']}): the image frame cuts the person "
                f"({', '.join(entry['frame_cut'])} border); the fit will flag it: step back or "
                "widen the view",
                file=sys.stderr,
            )
    if result.missing:
        names = ", ".join(f"pose{k} ({POSTURE_NAMES[k - 1]})" for k in result.missing)
        found = len(POSTURE_NAMES) - len(result.missing)
        written = f"the others are written to {args.out}" if found else "no posture was found"
        print(
            f"error: posture(s) not found in the video: {names} (no still stretch between "
            f"the neighbouring postures matches with a score of at least {args.min_score}); "
            f"{written}",
            file=sys.stderr,
        )
        return 1
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
