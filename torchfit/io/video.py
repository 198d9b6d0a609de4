"""Video files as frames (OpenCV's decoders)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from torchfit.errors import DataError

__all__ = ["video_frame_count", "read_video"]


def _open(path: str | Path):
    import cv2

    path = Path(path)
    if not path.is_file():
        raise DataError(f"video not found: {path}")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise DataError(f"{path}: cannot be read as a video")
    return cap


def video_frame_count(path: str | Path) -> int:
    """The number of frames of a video (decoded, not the container's estimate).

    Raises:
        DataError: missing or unreadable file, or no frame.
    """
    cap = _open(path)
    n = 0
    while cap.grab():
        n += 1
    cap.release()
    if n == 0:
        raise DataError(f"{path}: the video has no frames")
    return n


def read_video(
    path: str | Path, size: tuple[int, int] | None = None, limit: int | None = None
) -> Iterator[torch.Tensor]:
    """The frames of a video in order, each (1, 3, H, W) float32 RGB in [0, 1].

    Args:
        path: the video file.
        size: expected ``(width, height)`` (DataError otherwise).
        limit: stop after this many frames.
    """
    cap = _open(path)
    k = 0
    try:
        while limit is None or k < limit:
            ok, bgr = cap.read()
            if not ok:
                return
            h, w = bgr.shape[:2]
            if size is not None and (w, h) != tuple(size):
                raise DataError(
                    f"{path}: frame {k} is {w}x{h}, the camera's is {size[0]}x{size[1]}"
                )
            rgb = np.ascontiguousarray(bgr[..., ::-1]).astype(np.float32) / 255.0
            yield torch.from_numpy(rgb).permute(2, 0, 1)[None]
            k += 1
    finally:
        cap.release()
