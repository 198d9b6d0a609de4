"""From a real camera to a subject folder: checkerboard calibration with the world frame on the
floor mark (:mod:`~torchfit.capture.calibrate`)."""

from torchfit.capture.calibrate import (
    MIN_BOARD_IMAGES,
    Board,
    Calibration,
    calibrate,
    draw_check,
    find_corners,
    parse_board,
)

__all__ = [
    "MIN_BOARD_IMAGES",
    "Board",
    "Calibration",
    "calibrate",
    "draw_check",
    "find_corners",
    "parse_board",
]
