"""From a real camera to a subject folder: checkerboard calibration with the world frame on the
floor mark (:mod:`~torchfit.capture.calibrate`), choosing the background and posture frames of
a capture video (:mod:`~torchfit.capture.offline`) and live guidance served on the loopback
interface (:mod:`~torchfit.capture.live`). Only the calibration is imported here: the other
two load the body model, import them where needed."""

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
