"""Binary morphology of silhouettes: opening, closing, largest region, hole filling.

Conventions:

- Opening and closing work on ``(B, 1, H, W)`` bool tensors (``True`` = person) on the input's
  device, with a ``k x k`` square structuring element (``k`` odd). They are computed as
  separable shifted OR/AND of bool tensors and equal ``kornia.morphology.opening/closing`` with
  ``torch.ones(k, k)`` on the float mask and ``border_type="geodesic"`` (outside the image is
  ignored; ``tests/image/test_morphology.py`` checks this).
- Connected regions and holes are computed by OpenCV on the CPU, one ``(H, W)`` NumPy mask at
  a time (any integer or bool dtype, non-zero = person). Regions are 8-connected; a hole is a
  4-connected background region that the flood from outside the image does not reach (the
  complement connectivity of 8-connected regions).
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
import torch

__all__ = [
    "binary_opening",
    "binary_closing",
    "largest_component",
    "fill_holes",
    "pack_mask",
    "unpack_mask",
]


def _shift_reduce(x: torch.Tensor, k: int, dim: int, dilate: bool) -> torch.Tensor:
    """Max (``dilate``) or min of ``x`` over a centred window of ``k`` pixels along ``dim``.

    Outside the image is ignored (kornia's ``border_type="geodesic"``).
    """
    out = x.clone()
    n = x.shape[dim]
    for off in range(1, k // 2 + 1):
        if off >= n:
            break
        for src, dst in ((slice(off, n), slice(0, n - off)), (slice(0, n - off), slice(off, n))):
            o, v = (
                out.narrow(dim, dst.start, dst.stop - dst.start),
                x.narrow(dim, src.start, src.stop - src.start),
            )
            if dilate:
                o |= v
            else:
                o &= v
    return out


def _binary_morphology(x: torch.Tensor, k: int, op: Literal["opening", "closing"]) -> torch.Tensor:
    """Opening or closing of a bool ``(B, 1, H, W)`` mask by a ``k x k`` square.

    Kornia's grey-level morphology unfolds ``k * k`` values per pixel, which at 720x576 costs
    more than the rest of the segmentation chain; for a flat square on a binary mask the
    separable form is exact.
    """
    first, second = (False, True) if op == "opening" else (True, False)
    for dilate in (first, second):
        x = _shift_reduce(_shift_reduce(x, k, 2, dilate), k, 3, dilate)
    return x


def binary_opening(masks: torch.Tensor, kernel: int) -> torch.Tensor:
    """Opening (erosion, then dilation) by a ``kernel x kernel`` square.

    Args:
        masks: ``(B, 1, H, W)`` bool.
        kernel: side of the square element in pixels (odd).

    Returns:
        ``(B, 1, H, W)`` bool, same device.
    """
    return _binary_morphology(masks, kernel, "opening")


def binary_closing(masks: torch.Tensor, kernel: int) -> torch.Tensor:
    """Closing (dilation, then erosion) by a ``kernel x kernel`` square.

    Args:
        masks: ``(B, 1, H, W)`` bool.
        kernel: side of the square element in pixels (odd).

    Returns:
        ``(B, 1, H, W)`` bool, same device.
    """
    return _binary_morphology(masks, kernel, "closing")


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected region of one mask.

    Ties go to the region OpenCV labels first (the first in raster order).

    Args:
        mask: ``(H, W)`` NumPy mask (bool or integer, non-zero = region).

    Returns:
        ``(H, W)`` bool, ``True`` on the largest region (all ``False`` if there is none).
    """
    binary = (np.asarray(mask) != 0).astype(np.uint8)
    # the areas by counting labels: OpenCV's statistics cost several times the labelling
    # itself on a mask with many speckles
    n, labels = cv2.connectedComponents(binary, connectivity=8)
    if n <= 1:
        return np.zeros(binary.shape, dtype=bool)
    area = np.bincount(labels.ravel(), minlength=n)
    biggest = 1 + int(np.argmax(area[1:]))
    return labels == biggest


def fill_holes(mask: np.ndarray, max_fraction: float | None = None) -> np.ndarray:
    """Fill the holes of one mask (background regions the silhouette encloses).

    Args:
        mask: ``(H, W)`` NumPy mask (bool or integer, non-zero = person).
        max_fraction: fill only holes of at most this fraction of the filled silhouette's area
            (holes included); None fills every hole.

    Returns:
        ``(H, W)`` bool, ``mask`` with its (small enough) holes set.
    """
    binary = (np.asarray(mask) != 0).astype(np.uint8)
    flood = np.pad(binary, 1)
    cv2.floodFill(flood, None, (0, 0), 1)
    holes = (1 - flood[1:-1, 1:-1]).astype(np.uint8)
    if max_fraction is None:
        return (binary | holes).astype(bool)
    limit = max_fraction * (int(binary.sum()) + int(holes.sum()))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(holes, connectivity=4)
    small = np.zeros(n, dtype=np.uint8)
    small[1:] = stats[1:, cv2.CC_STAT_AREA] <= limit
    return (binary | small[labels]).astype(bool)


def pack_mask(mask: np.ndarray) -> tuple:
    """An (H, W) mask (non-zero = person) as its shape, bounding box and the box's bits: a few
    KB where the whole mask is hundreds (small to keep or to send to another process)."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if not len(rows):
        return mask.shape, (0, 0, 0, 0), b""
    box = (rows[0], rows[-1] + 1, cols[0], cols[-1] + 1)
    return mask.shape, box, np.packbits(mask[box[0] : box[1], box[2] : box[3]] > 0).tobytes()


def unpack_mask(packed: tuple) -> np.ndarray:
    """:func:`pack_mask` undone: the (H, W) uint8 mask, 255 inside, 0 outside."""
    shape, (v0, v1, u0, u1), bits = packed
    mask = np.zeros(shape, np.uint8)
    n = (v1 - v0) * (u1 - u0)
    if n:
        crop = np.unpackbits(np.frombuffer(bits, np.uint8), count=n).reshape(v1 - v0, u1 - u0)
        mask[v0:v1, u0:u1] = crop * np.uint8(255)
    return mask
