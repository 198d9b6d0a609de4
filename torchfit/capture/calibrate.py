"""Camera calibration from checkerboard images, with the world frame on the floor mark.

Intrinsics and distortion (OpenCV's five coefficients ``k1 k2 p1 p2 k3``) come from
``cv2.findChessboardCorners``, ``cv2.cornerSubPix`` and ``cv2.calibrateCamera`` on images of a
checkerboard held in front of the camera. One more image of the same board lying flat on the
floor where the person will stand fixes the world frame (design.md section 2):

- the origin is the centre of the board's inner-corner grid (the floor mark);
- z points up (towards the camera's side of the floor);
- x runs along the board's columns (the ``COLS`` direction of ``COLSxROWS``), from the end whose
  outer corner squares are dark to the end whose are light; y follows (right-handed).

The direction of x is unique where the board is not symmetric under a half turn: one of
``COLS`` and ``ROWS`` (inner corners) odd and the other even, as on the usual 9x6 board. On a
symmetric board (both odd or both even) the two ends look alike and x may point either way.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from torchfit.camera import Camera
from torchfit.errors import ConfigError, DataError
from torchfit.io.images import read_image

__all__ = [
    "MIN_BOARD_IMAGES",
    "Board",
    "parse_board",
    "find_corners",
    "Calibration",
    "calibrate",
    "calibrate_intrinsics",
    "floor_extrinsics",
    "draw_check",
]

#: Fewest images with a board found that an intrinsic calibration needs.
MIN_BOARD_IMAGES = 5

#: The board is searched for in a copy of the image at most this many pixels wide and high
#: (the corners are then refined at full resolution): on larger images OpenCV's search took up
#: to 20 s per image and missed boards it finds in the smaller copy.
DETECT_MAX_PX = 1280


@dataclass(frozen=True)
class Board:
    """A checkerboard: inner corners ``cols`` x ``rows`` and the side of a square, metres."""

    cols: int
    rows: int
    square_m: float

    def object_points(self) -> np.ndarray:
        """(cols * rows, 3) float32 corner positions on the board (z = 0), row by row, in
        OpenCV's order: corner ``(i, j)`` at ``(i * square, j * square, 0)``."""
        j, i = np.mgrid[0 : self.rows, 0 : self.cols]
        pts = np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1) * self.square_m
        return pts.astype(np.float32)

    @property
    def centre(self) -> np.ndarray:
        """(3,) the centre of the inner-corner grid in board coordinates."""
        return np.array([(self.cols - 1) / 2, (self.rows - 1) / 2, 0.0]) * self.square_m


def parse_board(text: str) -> Board:
    """``checkerboard:COLSxROWS:SQUARE_M`` (inner corners; the square's side in metres).

    Raises:
        ConfigError: naming what is wrong with ``text``.
    """
    m = re.fullmatch(r"checkerboard:(\d+)x(\d+):([0-9.eE+-]+)", text.strip())
    if m is None:
        raise ConfigError(
            f"--board: expected checkerboard:COLSxROWS:SQUARE_M (inner corners, metres), e.g. "
            f"checkerboard:9x6:0.025, got {text!r}"
        )
    cols, rows = int(m.group(1)), int(m.group(2))
    try:
        square = float(m.group(3))
    except ValueError:
        square = float("nan")
    if cols < 2 or rows < 2:
        raise ConfigError(f"--board: expected at least 2x2 inner corners, got {cols}x{rows}")
    if not math.isfinite(square) or square <= 0:
        raise ConfigError(f"--board: the square's side must be a positive length, got {m.group(3)}")
    return Board(cols, rows, square)


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image


def _sample(grey: np.ndarray, point: np.ndarray) -> float:
    h, w = grey.shape
    x, y = int(round(point[0])), int(round(point[1]))
    x0, x1, y0, y1 = max(x - 1, 0), min(x + 2, w), max(y - 1, 0), min(y + 2, h)
    if x0 >= x1 or y0 >= y1:
        return float("nan")
    return float(grey[y0:y1, x0:x1].mean())


def _canonical(corners: np.ndarray, grey: np.ndarray, board: Board) -> np.ndarray:
    """The corners in the order whose first corner's outer square is darker than the last
    corner's (a half turn of OpenCV's order otherwise)."""
    p = corners.reshape(-1, 2)
    c = board.cols
    first = p[0] - 0.5 * (p[1] - p[0]) - 0.5 * (p[c] - p[0])
    last = p[-1] + 0.5 * (p[-1] - p[-2]) + 0.5 * (p[-1] - p[-1 - c])
    if _sample(grey, first) > _sample(grey, last):
        return corners[::-1].copy()
    return corners


def find_corners(image: np.ndarray, board: Board) -> np.ndarray | None:
    """The board's inner corners in an image, refined to sub-pixel precision.

    Args:
        image: (H, W, 3) RGB or (H, W) grey uint8.
        board: the checkerboard.

    Returns:
        (cols * rows, 1, 2) float32 pixel positions in the canonical order of the module
        docstring, or None where the whole board was not found, or where a corner lies within the
        refinement window of the image frame (a board the frame cuts).
    """
    grey = _grey(image)
    h, w = grey.shape
    shrink = min(1.0, DETECT_MAX_PX / max(h, w))
    search = grey
    if shrink < 1.0:
        search = cv2.resize(grey, None, fx=shrink, fy=shrink, interpolation=cv2.INTER_AREA)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(search, (board.cols, board.rows), flags=flags)
    if not found:
        return None
    if shrink < 1.0:  # back to full-resolution pixels (pixel centres at integers)
        corners = ((corners + 0.5) / shrink - 0.5).astype(np.float32)
    # the refinement window: under half the smallest spacing between neighbouring corners
    pts = corners.reshape(board.rows, board.cols, 2)
    spacing = min(
        np.linalg.norm(np.diff(pts, axis=1), axis=2).min(),
        np.linalg.norm(np.diff(pts, axis=0), axis=2).min(),
    )
    half = int(max(2, min(11, spacing * 0.4)))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    corners = cv2.cornerSubPix(grey, corners, (half, half), (-1, -1), criteria)
    # a board the image frame cuts: OpenCV may still return the whole grid, its cut-off
    # corners placed on the frame (one was 8 px off its true place): not a board found
    xy = corners.reshape(-1, 2)
    inside = (xy >= half) & (xy <= np.array([w - 1 - half, h - 1 - half]))
    if not inside.all():
        return None
    return _canonical(corners, grey, board)


@dataclass
class Calibration:
    """A calibrated camera and how well it fits.

    Attributes:
        camera: the camera (B = 1, float64), world frame on the floor mark.
        rms_px: reprojection RMS of the intrinsic calibration (pixels); None when the
            intrinsics were given.
        floor_rms_px: reprojection RMS of the floor board with the final camera.
        used: the board images used for the intrinsics.
        without_board: the images in which the board was not found.
        warnings: what is off but did not stop the calibration.
    """

    camera: Camera
    rms_px: float | None
    floor_rms_px: float
    used: list[Path] = field(default_factory=list)
    without_board: list[Path] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def height_m(self) -> float:
        """The camera centre's height above the floor, metres."""
        return float(self.camera.centre[0, 2])

    @property
    def distance_m(self) -> float:
        """The camera centre's horizontal distance from the floor mark, metres."""
        return float(torch.linalg.vector_norm(self.camera.centre[0, :2]))


def calibrate_intrinsics(
    images: list[Path], board: Board
) -> tuple[np.ndarray, np.ndarray, float, tuple[int, int], list[Path], list[Path]]:
    """``K`` (3, 3), ``dist`` (5,), the RMS in pixels, the image size ``(w, h)``, the images
    used and those without a board.

    Raises:
        DataError: no images, images of different sizes, or fewer than
            :data:`MIN_BOARD_IMAGES` with the board found (the message lists those without).
    """
    if not images:
        raise DataError("no board images given")
    obj, pts, used, missing = [], [], [], []
    size = None
    for path in images:
        image = read_image(path)
        h, w = image.shape[:2]
        if size is None:
            size = (w, h)
        elif (w, h) != size:
            raise DataError(
                f"{path}: board image is {w}x{h} pixels, the first one is {size[0]}x{size[1]}"
            )
        corners = find_corners(image, board)
        if corners is None:
            missing.append(path)
            continue
        obj.append(board.object_points())
        pts.append(corners)
        used.append(path)
    if len(used) < MIN_BOARD_IMAGES:
        listed = ", ".join(p.name for p in missing) or "none"
        raise DataError(
            f"the {board.cols}x{board.rows} board was found in {len(used)} of {len(images)} "
            f"images, at least {MIN_BOARD_IMAGES} are needed; no board in: {listed}"
        )
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 200, 1e-12)
    rms, K, dist, _, _ = cv2.calibrateCamera(obj, pts, size, None, None, criteria=criteria)
    return K, dist.ravel()[:5], float(rms), size, used, missing


def floor_extrinsics(
    floor: Path, board: Board, K: np.ndarray, dist: np.ndarray, size: tuple[int, int] | None
) -> tuple[np.ndarray, np.ndarray, float]:
    """World -> camera ``R`` (3, 3), ``t`` (3,) from the board on the floor, and the floor
    image's reprojection RMS (pixels).

    Raises:
        DataError: the board is not found in ``floor``, or its size differs from ``size``.
    """
    image = read_image(floor)
    h, w = image.shape[:2]
    if size is not None and (w, h) != tuple(size):
        raise DataError(
            f"{floor}: floor image is {w}x{h} pixels, the camera's images are {size[0]}x{size[1]}"
        )
    corners = find_corners(image, board)
    if corners is None:
        raise DataError(f"{floor}: the {board.cols}x{board.rows} board was not found")
    obj = board.object_points()
    ok, rvec, tvec = cv2.solvePnP(obj, corners, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise DataError(f"{floor}: the board's pose could not be solved")
    rvec, tvec = cv2.solvePnPRefineLM(obj, corners, K, dist, rvec, tvec)
    Rb, _ = cv2.Rodrigues(rvec)
    tb = tvec.ravel()
    # world = M (board - centre); M flips y and z where the camera is below the board's +z
    centre_b = -Rb.T @ tb
    M = np.diag([1.0, -1.0, -1.0]) if centre_b[2] < 0 else np.eye(3)
    R = Rb @ M
    t = Rb @ board.centre + tb
    reproj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(((reproj.reshape(-1, 2) - corners.reshape(-1, 2)) ** 2).sum(1).mean()))
    return R, t, rms


def calibrate(
    board: Board,
    floor: Path,
    images: list[Path] | None = None,
    intrinsics: Camera | None = None,
    max_rms_px: float = 1.0,
) -> Calibration:
    """Calibrate a camera: intrinsics from ``images`` (or given), world frame from ``floor``.

    Args:
        board: the checkerboard.
        floor: the image of the board lying flat on the floor at the mark.
        images: board images for the intrinsics (ignored when ``intrinsics`` is given).
        intrinsics: a camera whose ``K``, ``dist`` and ``image_size`` are kept.
        max_rms_px: a reprojection RMS above this gives a warning.

    Raises:
        DataError: fewer than :data:`MIN_BOARD_IMAGES` boards found (listing the images
        without one), no board in ``floor``, images of different sizes.
    """
    rms = None
    used: list[Path] = []
    missing: list[Path] = []
    if intrinsics is not None:
        K = intrinsics.K[0].double().numpy()
        dist = intrinsics.dist[0].double().numpy()
        size = intrinsics.image_size
    else:
        K, dist, rms, size, used, missing = calibrate_intrinsics(list(images or []), board)
    R, t, floor_rms = floor_extrinsics(Path(floor), board, K, dist, size)
    camera = Camera(
        K=torch.from_numpy(np.asarray(K, np.float64)),
        dist=torch.from_numpy(np.asarray(dist, np.float64).copy()),
        R=torch.from_numpy(R.astype(np.float64)),
        t=torch.from_numpy(t.astype(np.float64)),
        image_size=(int(size[0]), int(size[1])),
    )
    result = Calibration(camera, rms, floor_rms, used, missing)
    for what, value in (("calibration", rms), ("floor image", floor_rms)):
        if value is not None and value > max_rms_px:
            result.warnings.append(
                f"{what} reprojection RMS is {value:.2f} px (above {max_rms_px:g} px): check the "
                "board images (blur, a bent board, wrong --board size)"
            )
    return result


def draw_check(image: np.ndarray, camera: Camera, axis_m: float = 0.5) -> np.ndarray:
    """The floor image with the world axes (x red, y green, z blue, ``axis_m`` long) and a
    1.8 m pole at the origin (yellow, a tick every 0.5 m) drawn in.

    Args:
        image: (H, W, 3) RGB uint8.
        camera: the calibrated camera (B = 1).

    Returns:
        (H, W, 3) RGB uint8, a copy.
    """
    K = camera.K[0].double().numpy()
    dist = camera.dist[0].double().numpy()
    rvec, _ = cv2.Rodrigues(camera.R[0].double().numpy())
    tvec = camera.t[0].double().numpy()
    ticks = [0.5, 1.0, 1.5, 1.8]
    pts = np.array(
        [[0, 0, 0], [axis_m, 0, 0], [0, axis_m, 0], [0, 0, axis_m], [0, 0, 1.8]]
        + [[0, 0, z] for z in ticks],
        np.float64,
    )
    uv, _ = cv2.projectPoints(pts, rvec, tvec, K, dist)
    uv = uv.reshape(-1, 2)
    out = np.ascontiguousarray(image.copy())
    scale = max(1, round(max(image.shape[:2]) / 500))

    def p(k: int) -> tuple[int, int]:
        return int(round(uv[k, 0] * 16)), int(round(uv[k, 1] * 16))

    aa = dict(lineType=cv2.LINE_AA, shift=4)
    cv2.line(out, p(0), p(4), (255, 220, 0), 3 * scale, **aa)
    for k in range(5, 5 + len(ticks)):
        cv2.circle(out, p(k), 16 * 3 * scale, (255, 220, 0), -1, **aa)
    for k, colour in ((1, (255, 0, 0)), (2, (0, 200, 0)), (3, (0, 0, 255))):
        cv2.line(out, p(0), p(k), colour, 2 * scale, **aa)
    return out
