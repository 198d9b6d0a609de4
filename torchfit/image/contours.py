"""Ordered outer contours of silhouettes and their rasterisation.

Conventions (see ``docs/design.md`` section 2):

- Masks are ``(B, 1, H, W)`` bool tensors, ``B`` first (``True`` = person); a single mask given
  to :func:`trace_outer_contour` is ``(H, W)``.
- Pixel ``(0, 0)`` is the centre of the top-left pixel; ``u`` grows to the right, ``v`` down.
  Contour pixels are written ``(u, v)``, ``int64``.
"""

from __future__ import annotations

import numpy as np
import torch

from torchfit.errors import ShapeError, check_shape

__all__ = [
    "trace_outer_contour",
    "outer_contours",
    "contour_mask",
    "outline_mask",
    "on_image_frame",
    "contour_normals",
]

# The 8 neighbours, clockwise on screen (v down): E, SE, S, SW, W, NW, N, NE, as (du, dv).
_DIRS = ((1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1))


def _check_masks(name: str, masks: torch.Tensor) -> None:
    check_shape(name, masks, ("B", 1, "H", "W"))
    if masks.dtype != torch.bool:
        raise ShapeError(f"{name}: expected a bool mask tensor, got dtype {masks.dtype}")


def trace_outer_contour(mask: np.ndarray | torch.Tensor) -> torch.Tensor:
    """Follow the outer border of one 8-connected region, in order.

    The region is the one holding the first foreground pixel in raster order (top row first,
    then left to right); pass a cleaned mask with a single region. The border is followed as in
    Suzuki and Abe's border following (CVGIP 30(1), 1985), which is what ``cv2.findContours``
    does: it starts at that first pixel, runs counter-clockwise on screen, and lists a pixel
    again each time the border passes it (one-pixel-wide spurs are walked out and back).

    Args:
        mask: ``(H, W)`` mask (bool or integer, non-zero = region), array or tensor.

    Returns:
        ``(N, 2)`` ``int64`` tensor of ``(u, v)`` contour pixels, ``N = 0`` for an empty mask.

    Raises:
        ShapeError: if ``mask`` is not 2-D.
    """
    if isinstance(mask, torch.Tensor):
        mask = mask.detach().cpu().numpy()
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ShapeError(f"mask: expected shape (H, W), got {mask.shape}")
    h, w = mask.shape
    padded = np.zeros((h + 2, w + 2), dtype=np.uint8)
    padded[1:-1, 1:-1] = mask != 0
    flat = padded.tobytes()  # indexing bytes gives ints: fast in the Python loop below
    start = flat.find(b"\x01")
    if start < 0:
        return torch.zeros((0, 2), dtype=torch.int64)
    wp = w + 2
    offsets = [du + dv * wp for du, dv in _DIRS]
    direction_of = {off: d for d, off in enumerate(offsets)}

    # First step: search clockwise from the west neighbour (background, since the start pixel
    # is the first in raster order) for the last pixel of the border, p1.
    p1 = -1
    for k in range(8):
        q = start + offsets[(4 + k) % 8]
        if flat[q]:
            p1 = q
            break
    chain = [start]
    if p1 >= 0:
        prev, cur = p1, start
        while True:
            d = direction_of[prev - cur]
            nxt = prev
            for k in range(1, 8):  # counter-clockwise, starting after the previous pixel
                q = cur + offsets[(d - k) % 8]
                if flat[q]:
                    nxt = q
                    break
            if nxt == start and cur == p1:
                break
            chain.append(nxt)
            prev, cur = cur, nxt
    idx = np.asarray(chain, dtype=np.int64)
    return torch.from_numpy(np.stack([idx % wp - 1, idx // wp - 1], axis=1))


def outer_contours(masks: torch.Tensor) -> list[torch.Tensor]:
    """Ordered outer contour of each mask of a batch (see :func:`trace_outer_contour`).

    Args:
        masks: ``(B, 1, H, W)`` bool.

    Returns:
        ``B`` tensors of shape ``(N_b, 2)``, ``int64`` ``(u, v)`` pixels on ``masks.device``.
    """
    _check_masks("masks", masks)
    host = masks[:, 0].detach().cpu().numpy()
    return [trace_outer_contour(m).to(masks.device) for m in host]


def contour_mask(masks: torch.Tensor) -> torch.Tensor:
    """Rasterise the ordered outer contour of each mask.

    Args:
        masks: ``(B, 1, H, W)`` bool.

    Returns:
        ``(B, 1, H, W)`` bool, ``True`` on the pixels of :func:`outer_contours`.
    """
    _check_masks("masks", masks)
    return outline_mask(outer_contours(masks), masks.shape[-2], masks.shape[-1], masks.device)


def outline_mask(
    outlines: list[torch.Tensor], height: int, width: int, device: torch.device | str = "cpu"
) -> torch.Tensor:
    """Rasterise traced outlines, one per image (e.g. :func:`trace_outer_contour`'s).

    Args:
        outlines: ``B`` tensors ``(N_b, 2)`` of ``(u, v)`` pixels.
        height, width: the image size.
        device: where the mask goes.

    Returns:
        ``(B, 1, H, W)`` bool, ``True`` on the outlines' pixels.
    """
    out = torch.zeros(len(outlines), 1, height, width, dtype=torch.bool, device=device)
    for b, pts in enumerate(outlines):
        pts = pts.to(device)
        out[b, 0, pts[:, 1], pts[:, 0]] = True
    return out


def on_image_frame(pixels, width: int, height: int):
    """Which ``(N, 2)`` integer ``(u, v)`` pixels (array or tensor) lie on the image's outermost
    rows or columns: where the frame cuts a silhouette, an outline there is the picture's edge,
    not the silhouette's. Returns an ``(N,)`` bool of the same kind."""
    u, v = pixels[:, 0], pixels[:, 1]
    return (u <= 0) | (u >= width - 1) | (v <= 0) | (v >= height - 1)


def contour_normals(contour: torch.Tensor, span: int = 3) -> torch.Tensor:
    """Unit outward normals of an ordered outer contour (:func:`trace_outer_contour`'s order).

    The tangent at pixel ``i`` is ``contour[i + span] - contour[i - span]`` (cyclically); the
    trace runs counter-clockwise on screen (``v`` down), so the outward normal is the tangent
    turned a quarter clockwise on screen, ``(-t_v, t_u)``. Where the tangent vanishes (a spur
    walked out and back), the normal is zero.

    Args:
        contour: ``(N, 2)`` ordered ``(u, v)`` pixels.
        span: half the tangent's base, in contour pixels.

    Returns:
        ``(N, 2)`` float32 unit normals (zero where undefined).
    """
    check_shape("contour", contour, ("N", 2))
    c = contour.to(torch.float32)
    if c.shape[0] < 3:
        return torch.zeros_like(c)
    s = min(span, (c.shape[0] - 1) // 2)
    t = torch.roll(c, -s, 0) - torch.roll(c, s, 0)
    n = torch.stack([-t[:, 1], t[:, 0]], 1)
    norm = n.norm(dim=1, keepdim=True)
    return torch.where(norm > 0, n / norm.clamp_min(1e-12), torch.zeros_like(n))
