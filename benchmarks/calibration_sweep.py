"""Calibration on many random cameras: checkerboard images rendered through seeded random
distorted cameras (``torchfit.synth.board.random_camera``, as ``tests/test_calibrate.py``
draws them), calibrated with
``torchfit.capture.calibrate``, against issue-level limits (focal length 0.5 %, principal point
2 px, camera centre 1 cm).

    python benchmarks/calibration_sweep.py --size 1920x1080 --seeds 2000 2012 [--images 14]

The focal length is drawn in proportion to the image's height (650-1000 px at 576 rows), the
principal point within 20 px of the centre, the camera 1.8-2.6 m from the mark and 1.6-2.3 m
high, looking at a point 0.5 m above it. Prints one row per seed and the count within limits.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchfit.capture.calibrate import Board, calibrate  # noqa: E402
from torchfit.synth.board import random_camera, write_board_images  # noqa: E402

#: the tests' board: 9x6 inner corners, 6 cm squares
BOARD = Board(9, 6, 0.06)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", default="720x576", help="WIDTHxHEIGHT")
    p.add_argument("--seeds", type=int, nargs=2, default=(0, 10), metavar=("FIRST", "END"))
    p.add_argument("--images", type=int, default=14, help="board images per camera")
    args = p.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    within = 0
    print("| seed | boards used | focal % | principal point px | centre cm | RMS px | s |")
    print("|--:|--:|--:|--:|--:|--:|--:|")
    for seed in range(*args.seeds):
        rng = np.random.default_rng(seed)
        truth = random_camera(rng, size)
        with tempfile.TemporaryDirectory() as d:
            folder = write_board_images(
                truth, Path(d), BOARD.cols, BOARD.rows, BOARD.square_m, args.images, rng
            )
            t = time.perf_counter()
            boards = sorted((folder / "boards").glob("*.png"))
            try:
                r = calibrate(BOARD, folder / "floor.png", boards)
            except Exception as exc:  # a failed calibration is a row of the table
                print(f"| {seed} | error: {exc} | | | | | |")
                continue
            took = time.perf_counter() - t
        K, K0 = r.camera.K[0], truth.K[0]
        focal = 100 * max(abs(float(K[i, i] / K0[i, i] - 1)) for i in (0, 1))
        pp = float(torch.linalg.vector_norm(K[:2, 2] - K0[:2, 2]))
        centre = 100 * float(torch.linalg.vector_norm(r.camera.centre - truth.centre))
        within += focal < 0.5 and pp < 2.0 and centre < 1.0
        print(
            f"| {seed} | {len(r.used)} of {len(boards)} | {focal:.3f} | {pp:.2f} | {centre:.2f} "
            f"| {r.rms_px:.3f} | {took:.1f} |"
        )
    print(f"\n{within} of {args.seeds[1] - args.seeds[0]} cameras within all three limits")


if __name__ == "__main__":
    main()
