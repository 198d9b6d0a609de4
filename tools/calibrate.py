"""Calibrate a camera from checkerboard images and fix the world frame on the floor mark.

    python tools/calibrate.py --images DIR --board checkerboard:COLSxROWS:SQUARE_M \
        --floor IMAGE --out camera.yaml
    python tools/calibrate.py --intrinsics camera.yaml --board checkerboard:COLSxROWS:SQUARE_M \
        --floor IMAGE --out camera.yaml

``COLSxROWS`` counts the board's inner corners; ``SQUARE_M`` is the side of a square in metres.
The first form takes the intrinsics and distortion from the board images in ``--images`` (the
board held in front of the camera at various angles, filling a good part of the view; at least
5 images with the whole board visible). The second keeps the intrinsics of an existing
``camera.yaml`` and only redoes the world frame (the camera was moved).

``--floor`` is one image of the same board lying flat on the floor where the person will
stand. The world origin is the centre of its inner-corner grid, z points up and x runs along
the board's columns, from the end whose outer corner squares are dark (use a board with one
odd and one even count of inner corners, such as 9x6, for a unique x). The tool prints the
reprojection RMS, the camera's height above the floor and its horizontal distance from the
mark, writes ``camera.yaml`` (design.md section 3) and a check image (default: beside
``--out``, ``<stem>_check.png``): the world axes (x red, y green, z blue, 0.5 m) and a 1.8 m
pole at the origin, drawn into the floor image. An RMS above 1 px gives a warning.

Exit codes: 0 calibrated; 2 bad arguments or too few boards found (the images without a board
are listed) or no board in the floor image; 3 the outputs cannot be written; 4 an input missing
or unreadable.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tqdm import tqdm  # noqa: E402

from torchfit.capture.calibrate import calibrate, draw_check, parse_board  # noqa: E402
from torchfit.errors import DataError, OutputError, TorchfitError  # noqa: E402
from torchfit.io.camera import load_camera, save_camera  # noqa: E402
from torchfit.io.images import list_images, read_image, write_image  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", type=Path, help="folder of checkerboard images (intrinsics)")
    src.add_argument("--intrinsics", type=Path, help="camera.yaml whose K and dist are kept")
    p.add_argument("--board", required=True, help="checkerboard:COLSxROWS:SQUARE_M")
    p.add_argument("--floor", required=True, type=Path, help="the board lying on the floor mark")
    p.add_argument("--out", required=True, type=Path, help="camera.yaml to write")
    p.add_argument("--check", type=Path, help="check image (default <out stem>_check.png)")
    p.add_argument(
        "--max-rms", type=float, default=1.0, help="warn above this RMS in pixels (default 1)"
    )
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        board = parse_board(args.board)
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        intrinsics = images = None
        if args.intrinsics is not None:
            intrinsics = load_camera(args.intrinsics)
        else:
            images = list_images(args.images)
            if not images:
                raise DataError(f"no images found in {args.images}")
        if not args.floor.is_file():
            raise DataError(f"floor image not found: {args.floor}")
        for path in [*(images or []), args.floor]:  # unreadable: an input error, not a board's
            read_image(path)
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 4
    try:
        with tqdm(total=1, desc="calibrate", unit="step", leave=False) as bar:
            result = calibrate(board, args.floor, images, intrinsics, args.max_rms)
            bar.update(1)
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    if result.without_board:
        names = ", ".join(p.name for p in result.without_board)
        print(f"board not found in {len(result.without_board)} image(s), not used: {names}")
    if result.rms_px is not None:
        print(f"intrinsics from {len(result.used)} images: reprojection RMS {result.rms_px:.3f} px")
    K = result.camera.K[0]
    print(
        f"fx {K[0, 0]:.2f}  fy {K[1, 1]:.2f}  cx {K[0, 2]:.2f}  cy {K[1, 2]:.2f}  "
        f"dist {[round(v, 5) for v in result.camera.dist[0].tolist()]}"
    )
    print(f"floor board: reprojection RMS {result.floor_rms_px:.3f} px")
    print(
        f"camera height above the floor {result.height_m:.3f} m, horizontal distance from the "
        f"mark {result.distance_m:.3f} m"
    )
    check = args.check or args.out.with_name(f"{args.out.stem}_check.png")
    try:
        save_camera(result.camera, args.out)
        write_image(check, draw_check(read_image(args.floor), result.camera))
    except (OutputError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 3
    print(f"wrote {args.out} and {check}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
