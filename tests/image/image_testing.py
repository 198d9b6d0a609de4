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


#: Shadow-test options under which colour alone decides (no texture test, no noise term): what
#: the shin scenes below need for the shins to pass as shadow.
COLOUR_SHADOW = dict(
    gamma=1.0,
    threshold=4.0,
    shadow_test=True,
    shadow_band=0.4,
    shadow_ratio=(0.5, 0.95),
    shadow_chroma=0.05,
    shadow_noise=0.0,
    shadow_min_texture=float("inf"),
)


def shin_scene(left: int = 15, shin_shade: float = 0.8, cast: bool = True) -> dict:
    """A grey floor (90 x 100); a blue trunk and thighs from column ``left``; shins
    ``shin_shade`` times the floor (0.8: an attenuated copy, what the shadow test calls a
    shadow); black shoes; with ``cast``, a cast shadow on the floor right of the right shoe.

    Returns a dict: ``frames`` (5, 3, H, W) background, ``image`` (1, 3, H, W), and the (H, W)
    masks ``body``, ``shins``, ``shoes``, ``cast``.
    """
    gen = torch.Generator().manual_seed(5)
    h, w = 90, 100
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    floor = torch.full((3, 1, 1), 0.6) * (1 + 0.05 * torch.sin(xx * 0.5) * torch.cos(yy * 0.4))
    frames = quantise((floor + 0.006 * torch.randn(5, 3, h, w, generator=gen)).clamp(0, 1))
    image = floor.clone()
    shadow = torch.zeros(h, w, dtype=torch.bool)
    if cast:
        shadow[70:86, 60:95] = True
        image[:, shadow] *= 0.7
    body = torch.zeros(h, w, dtype=torch.bool)
    body[5:55, left : left + 42] = True
    body[30:55, left + 15 : left + 27] = False  # the gap between the thighs
    shins = torch.zeros_like(body)
    shins[55:75, left : left + 15] = shins[55:75, left + 27 : left + 42] = True
    shoes = torch.zeros_like(body)
    shoes[75:85, left - 2 : left + 15] = shoes[75:85, left + 27 : left + 44] = True
    image[:, body] = torch.tensor([0.2, 0.3, 0.7]).view(3, 1)
    image[:, shins] = image[:, shins] * shin_shade
    image[:, shoes] = 0.05
    image = quantise((image + 0.006 * torch.randn(3, h, w, generator=gen)).clamp(0, 1))[None]
    return dict(frames=frames, image=image, body=body, shins=shins, shoes=shoes, cast=shadow)
