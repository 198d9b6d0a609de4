"""Video files as frames (OpenCV's decoders)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from torchfit.errors import DataError, OutputError

__all__ = ["video_frame_count", "read_video", "VideoWriter"]


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


class VideoWriter:
    """Write RGB frames to a Motion-JPEG ``.avi`` (OpenCV's own encoder, no codec to install).

    Use as a context manager; ``write`` takes ``(H, W, 3)`` uint8 RGB frames of one size. The
    file is written next to its final name and moved there when the writer closes without an
    error, so a killed run leaves no half-written video under that name.

    Raises:
        OutputError: the file cannot be opened for writing or a frame has another size.
    """

    def __init__(self, path: str | Path, fps: float) -> None:
        self.path = Path(path)
        self.fps = float(fps)
        self._tmp = self.path.with_name(f".{self.path.stem}.part{self.path.suffix}")
        self._writer = None
        self._size: tuple[int, int] | None = None

    def write(self, frame: np.ndarray) -> None:
        """Append one ``(H, W, 3)`` uint8 RGB frame (the first one sets the video's size)."""
        import cv2

        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
            raise OutputError(f"{self.path}: expected (H, W, 3) uint8 frames, got {frame.shape}")
        size = (frame.shape[1], frame.shape[0])
        if self._writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fourcc = cv2.VideoWriter_fourcc(*"MJPG")
            self._writer = cv2.VideoWriter(str(self._tmp), fourcc, self.fps, size)
            if not self._writer.isOpened():
                raise OutputError(f"{self.path}: cannot be opened for writing as a video")
            self._size = size
        elif size != self._size:
            w, h = self._size
            raise OutputError(f"{self.path}: frame of {size[0]}x{size[1]} in a {w}x{h} video")
        self._writer.write(np.ascontiguousarray(frame[:, :, ::-1]))

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._writer is None:
            return
        self._writer.release()
        if exc_type is None:
            self._tmp.replace(self.path)
        else:
            self._tmp.unlink(missing_ok=True)
