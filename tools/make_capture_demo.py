"""Synthetic stand-ins for a real capture: checkerboard images and a posture video.

    python tools/make_capture_demo.py --out DIR [--seed S] [--board checkerboard:9x6:0.12]
    python tools/make_capture_demo.py --out DIR --subject DATA/subject_000


Writes, for one synthetic subject and camera (torchfit.synth):

- ``DIR/boards/board01.png`` …: the board held in front of the camera (for the intrinsics)
  and ``DIR/floor.png``: the board lying on the floor mark (for the world frame), rendered
  through the camera with its lens distortion;
- ``DIR/video/frames/000000.png`` …: the empty room, then the subject walking onto the mark
  and holding the six postures in order with transitions; ``DIR/video/video.json`` (the held
  stretches), ``DIR/video/truth.json`` and ``DIR/video/original/`` (a subject folder made of
  the middle frame of each held stretch);
- ``DIR/true_camera.yaml``: the camera the images were rendered with (what
  ``tools/calibrate.py`` should recover).

``--subject`` films a subject of a dataset made by ``tools/make_subjects.py`` with the
default options (its ``synth.json`` names the seed and index): the same body, clothes, room,
light and camera; no board images then (that camera is too low to see the floor board; use
``true_camera.yaml``). ``DIR/video/original_clean/`` is ``original/`` with the posture images
rendered without sensor noise.

Needs the ``synth`` extra (anny). Exit codes: 0 written, 2 bad arguments, 3 not writable.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from torchfit.capture.calibrate import parse_board  # noqa: E402
from torchfit.errors import TorchfitError  # noqa: E402
from torchfit.io.camera import load_camera  # noqa: E402
from torchfit.synth.board import write_board_images  # noqa: E402
from torchfit.synth.options import SynthConfig  # noqa: E402
from torchfit.synth.video import make_video  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, type=Path, help="folder to write the demo into")
    parser.add_argument("--seed", type=int, default=7000, help="body, room and camera seed")
    parser.add_argument(
        "--board",
        default="checkerboard:9x6:0.12",
        help="checkerboard:COLSxROWS:SQUARE_M, inner corners and square size",
    )
    parser.add_argument("--boards", type=int, default=12, help="held board images (default 12)")
    parser.add_argument(
        "--subject", type=Path, help="film this dataset subject (a folder with synth.json)"
    )
    args = parser.parse_args(argv)
    subject = None
    if args.subject is not None:
        try:
            summary = json.loads((args.subject / "synth.json").read_text())
            subject = (int(summary["seed"]), int(summary["index"]))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            print(f"error: --subject {args.subject}: no usable synth.json ({exc})", file=sys.stderr)
            return 2
    try:
        board = parse_board(args.board)
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    # a camera high enough (2.0-2.2 m) to see the board on the floor at 3 m
    cfg = SynthConfig(stereo=False, camera_height_m=[2.0, 2.2], camera_distance_m=[3.0, 3.3])
    try:
        if subject is not None:
            with tqdm(total=1, desc="render", unit="part") as bar:
                make_video(args.out / "video", subject[0], SynthConfig(), subject=subject)
                shutil.copy(args.out / "video" / "camera.yaml", args.out / "true_camera.yaml")
                bar.update(1)
            print(f"wrote {args.out}")
            return 0
        with tqdm(total=2, desc="render", unit="part") as bar:
            make_video(args.out / "video", args.seed, cfg)
            bar.update(1)
            camera = load_camera(args.out / "video" / "camera.yaml")
            rng = np.random.default_rng([args.seed, 1])
            write_board_images(
                camera, args.out, board.cols, board.rows, board.square_m, args.boards, rng, first=1
            )
            shutil.copy(args.out / "video" / "camera.yaml", args.out / "true_camera.yaml")
            bar.update(1)
    except OSError as exc:
        print(f"error: cannot write {args.out}: {exc}", file=sys.stderr)
        return 3
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
