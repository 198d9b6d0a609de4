"""Helpers shared by the image tests."""

from __future__ import annotations

import cv2
import numpy as np
import torch
from scipy import ndimage

BIG = 10**9


def quantise(x: torch.Tensor) -> torch.Tensor:
    return (x * 255).round().clamp(0, 255) / 255


def naive_chamfer_34(seeds: np.ndarray) -> np.ndarray:
    """The textbook two-pass 3-4 chamfer transform (Borgefors 1986), one pixel at a time."""
    h, w = seeds.shape
    d = np.where(seeds, 0, BIG).astype(np.int64)
    for y in range(h):
        for x in range(w):
            for dy, dx, c in ((-1, -1, 4), (-1, 0, 3), (-1, 1, 4), (0, -1, 3)):
                yy, xx = y + dy, x + dx
                if 0 <= yy < h and 0 <= xx < w:
                    d[y, x] = min(d[y, x], d[yy, xx] + c)
    for y in range(h - 1, -1, -1):
        for x in range(w - 1, -1, -1):
            for dy, dx, c in ((1, 1, 4), (1, 0, 3), (1, -1, 4), (0, 1, 3)):
                yy, xx = y + dy, x + dx
                if 0 <= yy < h and 0 <= xx < w:
                    d[y, x] = min(d[y, x], d[yy, xx] + c)
    return d


def random_blob(rng: np.random.Generator, h: int, w: int, level: float = 0.52) -> np.ndarray:
    """A smooth random single 8-connected region (uint8 0/1), possibly with holes."""
    for _ in range(100):
        field = ndimage.gaussian_filter(rng.random((h, w)), 3)
        m = (field > level).astype(np.uint8)
        n, labels = cv2.connectedComponents(m, connectivity=8)
        if n >= 2:
            sizes = np.bincount(labels.ravel())[1:]
            return (labels == 1 + int(np.argmax(sizes))).astype(np.uint8)
    raise RuntimeError("no blob")

