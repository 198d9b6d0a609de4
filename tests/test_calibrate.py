"""Checkerboard calibration (torchfit.capture.calibrate, tools/calibrate.py) on board images
rendered through known cameras with lens distortion (torchfit.synth.board)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchfit.camera import Camera
from torchfit.capture.calibrate import Board, calibrate, find_corners, parse_board
from torchfit.errors import ConfigError, DataError
from torchfit.io.camera import load_camera, save_camera
from torchfit.io.images import read_image, write_image
from torchfit.synth.board import (
    random_board_pose,
    random_camera,
    render_board,
    write_board_images,
)

REPO = Path(__file__).resolve().parents[1]
SIZE = (720, 576)
BOARD = Board(9, 6, 0.06)


def _random_camera(rng: np.random.Generator, size: tuple[int, int] = SIZE) -> Camera:
    """A camera the test does not choose: focal length, principal point, distortion and
    position drawn from a seeded generator (:func:`torchfit.synth.board.random_camera`)."""
    return random_camera(rng, size)


def _render(camera: Camera, folder: Path, rng: np.random.Generator, n: int = 14) -> Path:
    return write_board_images(camera, folder, BOARD.cols, BOARD.rows, BOARD.square_m, n, rng)


@pytest.mark.parametrize("seed,size", [(101, SIZE), (202, SIZE), (303, SIZE), (404, (1920, 1080))])
def test_calibration_recovers_a_known_camera(tmp_path, seed, size):
    rng = np.random.default_rng(seed)
    truth = _random_camera(rng, size)
    folder = _render(truth, tmp_path, rng)
    result = calibrate(BOARD, folder / "floor.png", sorted((folder / "boards").glob("*.png")))
    assert len(result.used) >= 8, result.without_board
    K, K0 = result.camera.K[0], truth.K[0]
    assert abs(K[0, 0] / K0[0, 0] - 1) < 0.005 and abs(K[1, 1] / K0[1, 1] - 1) < 0.005
    assert torch.linalg.vector_norm(K[:2, 2] - K0[:2, 2]) < 2.0
    assert torch.linalg.vector_norm(result.camera.centre - truth.centre) < 0.01
    # the whole world frame, not only the centre: a point 1 m up and 0.5 m along x projects
    # where the true camera puts it
    from torchfit.camera import project_points

    pts = torch.tensor([[[0.5, 0.0, 1.0], [0.0, 0.3, 0.0]]], dtype=torch.float64)
    assert torch.allclose(project_points(pts, result.camera), project_points(pts, truth), atol=2.0)
    assert result.rms_px < 0.5 and result.floor_rms_px < 0.5 and result.warnings == []
    assert result.height_m == pytest.approx(float(truth.centre[0, 2]), abs=0.01)
    assert result.distance_m == pytest.approx(float(truth.centre[0, :2].norm()), abs=0.01)

    # camera.yaml round trip through the loader, and the --intrinsics variant
    save_camera(result.camera, tmp_path / "camera.yaml")
    loaded = load_camera(tmp_path / "camera.yaml")
    assert torch.equal(loaded.K, result.camera.K) and torch.equal(loaded.t, result.camera.t)
    again = calibrate(BOARD, folder / "floor.png", intrinsics=loaded)
    assert again.rms_px is None
    strict = calibrate(BOARD, folder / "floor.png", intrinsics=loaded, max_rms_px=1e-4)
    assert len(strict.warnings) == 1 and "floor image reprojection RMS" in strict.warnings[0]
    assert torch.linalg.vector_norm(again.camera.centre - truth.centre) < 0.01


def test_a_board_the_image_frame_cuts_is_not_found(tmp_path):
    """A 1920x1080 view whose board runs off the bottom of the image: OpenCV returns the whole
    grid with the cut-off corners on the frame (one 8-10 px from its true place, which moved
    that calibration's principal point by 6 px); find_corners reports no board there, and one
    where the board is in view."""
    rng = np.random.default_rng(2009)
    size = (1920, 1080)
    camera = _random_camera(rng, size)
    folder = _render(camera, tmp_path, rng, n=4)
    cut = read_image(folder / "boards" / "board03.png")
    grey = cut.mean(axis=2).astype(np.uint8)
    import cv2

    # OpenCV alone finds the whole grid, its last row on the frame
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(grey, (BOARD.cols, BOARD.rows), flags=flags)
    assert found and corners[..., 1].max() > size[1] - 12, corners[..., 1].max()
    assert find_corners(cut, BOARD) is None
    assert find_corners(read_image(folder / "boards" / "board00.png"), BOARD) is not None


def test_the_corner_order_is_canonical_under_a_half_turn(tmp_path):
    """The board turned by 180 degrees in the image gives the same corners, in the same board
    order (x from the end with dark outer squares)."""
    rng = np.random.default_rng(7)
    K = np.array([[800.0, 0, 360], [0, 800.0, 288], [0, 0, 1]])
    rvec, tvec = random_board_pose(
        rng, K, SIZE, BOARD.cols, BOARD.rows, BOARD.square_m, distance=(1.2, 1.3)
    )
    image = render_board(K, np.zeros(5), rvec, tvec, BOARD.cols, BOARD.rows, BOARD.square_m, SIZE)
    a = find_corners(image, BOARD).reshape(-1, 2)
    b = find_corners(np.ascontiguousarray(image[::-1, ::-1]), BOARD).reshape(-1, 2)
    b = np.array([SIZE[0] - 1, SIZE[1] - 1]) - b
    assert np.abs(a - b).max() < 0.2


def test_too_few_boards_lists_the_images_without_one(tmp_path):
    rng = np.random.default_rng(11)
    folder = _render(_random_camera(rng), tmp_path, rng, n=4)
    blank = np.full((SIZE[1], SIZE[0], 3), 120, np.uint8)
    write_image(folder / "boards" / "empty_wall.png", blank)
    with pytest.raises(DataError, match=r"found in 4 of 5 images.*no board in: empty_wall.png"):
        calibrate(BOARD, folder / "floor.png", sorted((folder / "boards").glob("*.png")))


def test_no_board_in_the_floor_image(tmp_path):
    rng = np.random.default_rng(12)
    camera = _random_camera(rng)
    write_image(tmp_path / "floor.png", np.full((SIZE[1], SIZE[0], 3), 90, np.uint8))
    with pytest.raises(DataError, match="floor.png: the 9x6 board was not found"):
        calibrate(BOARD, tmp_path / "floor.png", intrinsics=camera)


def test_board_spec_errors():
    assert parse_board("checkerboard:9x6:0.025") == Board(9, 6, 0.025)
    for bad in ("9x6", "checkerboard:9x6", "checkerboard:1x6:0.02", "checkerboard:9x6:0"):
        with pytest.raises(ConfigError, match="--board"):
            parse_board(bad)


def test_tool_writes_a_loadable_camera_and_a_check_image(tmp_path):
    rng = np.random.default_rng(404)
    truth = _random_camera(rng)
    folder = _render(truth, tmp_path, rng, n=8)
    out = tmp_path / "out" / "camera.yaml"
    cmd = [
        sys.executable,
        str(REPO / "tools" / "calibrate.py"),
        "--images",
        str(folder / "boards"),
        "--board",
        "checkerboard:9x6:0.06",
        "--floor",
        str(folder / "floor.png"),
        "--out",
        str(out),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "camera height above the floor" in done.stdout and "RMS" in done.stdout
    camera = load_camera(out)
    assert torch.linalg.vector_norm(camera.centre - truth.centre) < 0.01
    check = read_image(out.with_name("camera_check.png"))
    floor = read_image(folder / "floor.png")
    assert check.shape == floor.shape and (check != floor).any(axis=2).sum() > 500
    # a floor image without the board: exit 2, one line naming it
    write_image(tmp_path / "grey.png", np.full((SIZE[1], SIZE[0], 3), 90, np.uint8))
    cmd[cmd.index("--floor") + 1] = str(tmp_path / "grey.png")
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 2 and "grey.png: the 9x6 board was not found" in done.stderr
    # an unreadable floor image is bad input (exit 4), not a board the image lacks
    (tmp_path / "broken.png").write_bytes(b"not a png")
    cmd[cmd.index("--floor") + 1] = str(tmp_path / "broken.png")
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 4 and "broken.png" in done.stderr, done.stderr
