"""Precompute reference projections with ``cv2.projectPoints`` for tests/test_camera.py.

Writes ``tests/data/camera_reference.npz``: a few random cameras (focal lengths, principal
points, distortion with radial and tangential terms, poses) and world points in front of
them, with the pixels OpenCV computes. Run from the repository root::

    python tools/make_camera_reference.py
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np


def make_reference(seed: int = 1234, n_cameras: int = 6, n_points: int = 50) -> dict:
    """Random cameras and points, and the pixels ``cv2.projectPoints`` gives for them."""
    rng = np.random.default_rng(seed)
    K = np.zeros((n_cameras, 3, 3))
    dist = np.zeros((n_cameras, 5))
    R = np.zeros((n_cameras, 3, 3))
    t = np.zeros((n_cameras, 3))
    points = np.zeros((n_cameras, n_points, 3))
    pixels = np.zeros((n_cameras, n_points, 2))
    for c in range(n_cameras):
        fx, fy = rng.uniform(600, 1200, size=2)
        cx, cy = rng.uniform(300, 420), rng.uniform(240, 330)
        K[c] = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
        if c == 0:
            dist[c] = 0.0  # pure pinhole
        else:
            dist[c] = [
                rng.uniform(-0.3, 0.3),
                rng.uniform(-0.2, 0.2),
                rng.uniform(-0.01, 0.01),
                rng.uniform(-0.01, 0.01),
                rng.uniform(-0.1, 0.1),
            ]
        rvec = rng.normal(size=3)
        rvec *= rng.uniform(0.1, 2.5) / np.linalg.norm(rvec)
        R[c] = cv2.Rodrigues(rvec)[0]
        t[c] = rng.uniform(-0.5, 0.5, size=3) + [0, 0, 3.5]
        # points in the camera frame inside a +-25 degree cone, 2-5 m deep, then to world
        depth = rng.uniform(2.0, 5.0, size=n_points)
        xy = rng.uniform(-0.45, 0.45, size=(n_points, 2)) * depth[:, None]
        cam = np.concatenate([xy, depth[:, None]], axis=1)
        points[c] = (cam - t[c]) @ R[c]  # R^T (x_cam - t)
        px, _ = cv2.projectPoints(points[c], rvec, t[c], K[c], dist[c])
        pixels[c] = px.reshape(-1, 2)
    return {"K": K, "dist": dist, "R": R, "t": t, "points": points, "pixels": pixels}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="tests/data/camera_reference.npz")
    parser.add_argument("--seed", type=int, default=1234)
    args = parser.parse_args()
    ref = make_reference(args.seed)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, cv2_version=np.array(cv2.__version__), **ref)


if __name__ == "__main__":
    main()
