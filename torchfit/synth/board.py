"""Checkerboard images rendered through a known camera, for testing calibration.

Each square of the board (and the white margin around it) is a polygon whose edges are
subdivided before projection with ``cv2.projectPoints``, so lens distortion bends them as it
would a real board's; polygons are filled at ``supersample`` times the resolution and reduced
by area averaging (anti-aliased edges), then sensor noise is added.

The board's squares span ``[a, a + 1] x [b, b + 1]`` (in squares) for ``a = -1 … cols - 1``,
``b = -1 … rows - 1``, inner corner ``(i, j)`` at ``(i, j)``; square ``(a, b)`` is dark where
``a + b`` is even, so the outer square beyond inner corner ``(0, 0)`` is dark (the convention
of :mod:`torchfit.capture.calibrate`).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from torchfit.camera import Camera, look_at

__all__ = [
    "render_board",
    "random_board_pose",
    "floor_board_pose",
    "board_images",
    "random_camera",
    "write_board_images",
]


def _edge(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    s = np.linspace(0.0, 1.0, n, endpoint=False)[:, None]
    return a + s * (b - a)


def _polygon(x0: float, y0: float, x1: float, y1: float, n: int) -> np.ndarray:
    c = [np.array(p, float) for p in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))]
    return np.concatenate([_edge(c[k], c[(k + 1) % 4], n) for k in range(4)])


def render_board(
    K: np.ndarray,
    dist: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    cols: int,
    rows: int,
    square_m: float,
    size: tuple[int, int],
    rng: np.random.Generator | None = None,
    background: int = 110,
    noise: float = 1.5,
    supersample: int = 4,
    margin: float = 0.8,
) -> np.ndarray:
    """One image of a checkerboard posed ``(rvec, tvec)`` (board -> camera) in front of a
    camera ``K`` (3, 3), ``dist`` (5,).

    Args:
        cols, rows: inner corners; square_m: the square's side, metres.
        size: ``(width, height)`` of the image.
        rng: for the sensor noise (none without).
        background: grey level around the board.
        noise: standard deviation of the Gaussian sensor noise, grey levels.
        supersample: the fill's resolution factor.
        margin: the white margin around the squares, in squares.

    Returns:
        (H, W, 3) RGB uint8.
    """
    w, h = size
    f = supersample
    n = 12  # points per polygon edge, so that distortion bends the edges
    canvas = np.full((h * f, w * f), background, np.uint8)
    polys, shades = [], []
    outer = _polygon(-1 - margin, -1 - margin, cols + margin, rows + margin, 4 * n)
    polys.append(outer)
    shades.append(235)
    for a in range(-1, cols):
        for b in range(-1, rows):
            if (a + b) % 2 == 0:
                polys.append(_polygon(a, b, a + 1, b + 1, n))
                shades.append(25)
    K = np.asarray(K, np.float64)
    for poly, shade in zip(polys, shades, strict=True):
        obj = np.concatenate([poly * square_m, np.zeros((len(poly), 1))], axis=1)
        cam = (cv2.Rodrigues(np.asarray(rvec, np.float64))[0] @ obj.T).T + np.ravel(tvec)
        if (cam[:, 2] <= 1e-3).any():
            continue
        uv, _ = cv2.projectPoints(obj, rvec, tvec, K, np.asarray(dist, np.float64))
        # pixel centres at integers: the supersampled pixel (x + 0.5) * f - 0.5
        pts = ((uv.reshape(-1, 2) + 0.5) * f - 0.5) * 16
        cv2.fillPoly(canvas, [np.round(pts).astype(np.int32)], int(shade), cv2.LINE_8, shift=4)
    grey = cv2.resize(canvas.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    if rng is not None and noise > 0:
        grey = grey + rng.normal(0.0, noise, grey.shape)
    grey = np.clip(np.round(grey), 0, 255).astype(np.uint8)
    return np.repeat(grey[:, :, None], 3, axis=2)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * angle)[0]


def random_board_pose(
    rng: np.random.Generator,
    K: np.ndarray,
    size: tuple[int, int],
    cols: int,
    rows: int,
    square_m: float,
    distance: tuple[float, float] = (0.6, 1.2),
    tilt_deg: float = 35.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A board pose (``rvec`` (3,), ``tvec`` (3,), board -> camera) for calibration: the board
    facing the camera, tilted up to ``tilt_deg`` about a random in-plane axis, turned about its
    normal at random, at a random distance, its centre somewhere in the middle of the view."""
    axis = rng.normal(size=2)
    tilt = np.deg2rad(rng.uniform(10.0, tilt_deg))
    R = _rotation(np.array([axis[0], axis[1], 0.0]), tilt) @ _rotation(
        np.array([0.0, 0.0, 1.0]), rng.uniform(-np.pi, np.pi)
    )
    z = rng.uniform(*distance)
    w, h = size
    u, v = rng.uniform(0.35, 0.65) * w, rng.uniform(0.35, 0.65) * h
    centre_cam = np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
    centre_board = np.array([(cols - 1) / 2, (rows - 1) / 2, 0.0]) * square_m
    t = centre_cam - R @ centre_board
    return cv2.Rodrigues(R)[0].ravel(), t


def floor_board_pose(
    R_world: np.ndarray, t_world: np.ndarray, cols: int, rows: int, square_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """The pose (board -> camera) of a board lying on the floor with its inner-corner grid
    centred on the world origin, x along its columns and y against its rows (so that z, up,
    is x cross y), for a camera ``x_cam = R_world x_world + t_world``."""
    centre = np.array([(cols - 1) / 2, (rows - 1) / 2, 0.0]) * square_m
    M = np.diag([1.0, -1.0, -1.0])  # board -> world about the centre
    R = np.asarray(R_world, float) @ M
    t = np.asarray(t_world, float) - R @ centre
    return cv2.Rodrigues(R)[0].ravel(), t


def board_images(
    K: np.ndarray,
    dist: np.ndarray,
    R_world: np.ndarray,
    t_world: np.ndarray,
    size: tuple[int, int],
    cols: int,
    rows: int,
    square_m: float,
    n: int,
    rng: np.random.Generator,
) -> tuple[list[np.ndarray], np.ndarray]:
    """``n`` images of the board held in front of the camera (across 40 to 65 % of the
    image's width, tilted, turned) and one of it lying on the floor mark, for a camera ``K``,
    ``dist`` at ``x_cam = R_world x_world + t_world``; (H, W, 3) RGB uint8 each."""
    K = np.asarray(K, np.float64)
    width_m = (cols + 2.6) * square_m
    near, far = (K[0, 0] * width_m / (size[0] * share) for share in (0.65, 0.4))
    held = []
    for _ in range(n):
        rvec, tvec = random_board_pose(rng, K, size, cols, rows, square_m, distance=(near, far))
        held.append(render_board(K, dist, rvec, tvec, cols, rows, square_m, size, rng))
    rvec, tvec = floor_board_pose(R_world, t_world, cols, rows, square_m)
    return held, render_board(K, dist, rvec, tvec, cols, rows, square_m, size, rng)


def random_camera(rng: np.random.Generator, size: tuple[int, int] = (720, 576)) -> Camera:
    """A camera drawn from ``rng`` (B = 1, float64): focal length 650-1000 px at 576 rows, in
    proportion to the image's height, the principal point within 20 px of the centre, lens
    distortion (``k1`` -0.25..0.05, ``k2`` -0.05..0.15, small tangential terms), the camera
    1.8-2.6 m from the floor mark at any azimuth and 1.6-2.3 m high, looking at the point
    0.5 m above the mark."""
    f = rng.uniform(650.0, 1000.0) * size[1] / 576
    K = np.array(
        [
            [f, 0.0, size[0] / 2 + rng.uniform(-20, 20)],
            [0.0, f * rng.uniform(0.995, 1.005), size[1] / 2 + rng.uniform(-20, 20)],
            [0.0, 0.0, 1.0],
        ]
    )
    dist = np.array(
        [rng.uniform(-0.25, 0.05), rng.uniform(-0.05, 0.15), *rng.uniform(-1e-3, 1e-3, 2), 0.0]
    )
    azimuth = rng.uniform(-np.pi, np.pi)
    distance, height = rng.uniform(1.8, 2.6), rng.uniform(1.6, 2.3)
    centre = torch.tensor([[distance * np.cos(azimuth), distance * np.sin(azimuth), height]])
    R, t = look_at(centre, torch.tensor([[0.0, 0.0, 0.5]]))
    return Camera(
        K=torch.from_numpy(K),
        dist=torch.from_numpy(dist),
        R=R[0].double(),
        t=t[0].double(),
        image_size=size,
    )


def write_board_images(
    camera: Camera,
    folder: Path,
    cols: int,
    rows: int,
    square_m: float,
    n: int,
    rng: np.random.Generator,
    first: int = 0,
) -> Path:
    """:func:`board_images` of ``camera`` (B = 1) written as ``folder/boards/boardNN.png`` (NN
    from ``first``) and ``folder/floor.png`` (the layout ``tools/calibrate.py --images
    --floor`` reads); returns ``folder``."""
    from torchfit.io.images import write_image

    held, floor = board_images(
        camera.K[0].numpy(),
        camera.dist[0].numpy(),
        camera.R[0].numpy(),
        camera.t[0].numpy(),
        camera.image_size,
        cols,
        rows,
        square_m,
        n,
        rng,
    )
    for k, image in enumerate(held, start=first):
        write_image(folder / "boards" / f"board{k:02d}.png", image)
    write_image(folder / "floor.png", floor)
    return folder
