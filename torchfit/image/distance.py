"""Distance maps to contours (chamfer 3-4 and exact Euclidean) and their sub-pixel sampling.

Conventions (see ``docs/design.md`` section 2):

- Masks and maps are ``(B, 1, H, W)`` tensors, ``B`` first. A mask is ``bool`` (``True`` = person).
- Pixel ``(0, 0)`` is the centre of the top-left pixel; ``u`` grows to the right, ``v`` down.
  Points and contour pixels are written ``(u, v)``.
- Distance maps hold, at every pixel, the distance in **pixels** to the nearest pixel of the
  person's outer **contour** (not to the silhouette): the first paper (section 5) distance-
  transforms the contour. Where an image has no contour pixel at all the map is ``+inf``.

Two distance transforms are offered:

- :func:`chamfer_distance_transform`: Borgefors' 3-4 chamfer distance (axial step 3, diagonal
  step 4), exactly the result of the classic two-pass raster algorithm, in integer chamfer units
  (divide by 3 for pixels). Two implementations give the same integers. ``"rows"`` runs the two
  passes row after row, each row vectorised over batch and width, its in-row scan
  ``d[x] = min(d[x], d[x-1] + 3)`` done as one cummin (below); it is the faster on CPU for
  batches. ``"lines"`` has no loop over rows (suited to GPUs): for 3x3 masks the two-pass
  result is the length of the cheapest 8-connected path to a seed, and every cheapest path can be
  reordered into one run of diagonal steps followed by one run of axial steps along a row or a
  column. So the map is two rounds of 1-D "distance along a line" transforms,
  ``g[i] = min_k f[k] + c |i - k|``, first along both diagonal families (``c = 4``), then along
  rows and columns (``c = 3``); each 1-D transform is two ``torch.cummin`` scans, because
  ``min_{k<=i} f[k] + c (i - k) = c i + cummin(f[k] - c k)``.
- :func:`euclidean_distance_transform`: the exact Euclidean distance (as
  ``scipy.ndimage.distance_transform_edt``): exact distance to the nearest seed in the same
  column first, then a search along the row over growing offsets that stops as soon as no
  pixel can still improve.

:func:`sample_distance_map` reads the maps at sub-pixel points by bilinear interpolation; it
serves both a batch of maps sampled one per row and the fit's rows that each pick their
subject's map (``rows``).
"""

from __future__ import annotations

from typing import Literal

import torch

from torchfit.errors import ShapeError, check_shape
from torchfit.image.contours import _check_masks, contour_mask

__all__ = [
    "chamfer_distance_transform",
    "euclidean_distance_transform",
    "distance_map",
    "mask_to_distance_map",
    "sample_distance_map",
]

# "Infinite" distance for the integer transforms: far above any real distance in an image of up
# to ~100k pixels a side, and far below the int32/int64 limits after the offsets are added.
_INF = 1 << 20
_EDT_INF = 1 << 15  # the same for the exact transform, whose squares must fit in int32


def _line_transform(f: torch.Tensor, cost: int) -> torch.Tensor:
    """``g[..., i] = min_k f[..., k] + cost * |i - k|`` along the last dim, by two cummins.

    Exact for integer values held in an integer or float32 tensor (below ``2**24``).
    """
    n = f.shape[-1]
    ramp = torch.arange(n, device=f.device, dtype=f.dtype) * cost
    fwd = torch.cummin(f - ramp, -1).values + ramp
    bwd = torch.cummin((f + ramp).flip(-1), -1).values.flip(-1) - ramp
    return torch.minimum(fwd, bwd)


def _line_transform_cols(f: torch.Tensor, cost: int) -> torch.Tensor:
    """:func:`_line_transform` along dim -2 (scans run fastest over contiguous memory)."""
    return _line_transform(f.transpose(-1, -2).contiguous(), cost).transpose(-1, -2)


def _skew(f: torch.Tensor, fill: float) -> torch.Tensor:
    """``(N, H, W) -> (N, H, W + H - 1)`` with ``s[:, y, x + y] = f[:, y, x]``, ``fill`` elsewhere.

    Anti-diagonals (``x + y`` constant) of ``f`` become columns of the result.
    """
    n, h, w = f.shape
    row = w + h
    padded = torch.cat([f, f.new_full((n, h, h), fill)], dim=2).reshape(n, h * row)
    return padded[:, : h * (row - 1)].reshape(n, h, row - 1)


def _unskew(s: torch.Tensor, w: int) -> torch.Tensor:
    """Inverse of :func:`_skew`: ``(N, H, W + H - 1) -> (N, H, W)``."""
    n, h, _ = s.shape
    row = w + h
    flat = torch.cat([s.reshape(n, -1), s.new_zeros((n, h))], dim=1)
    return flat.reshape(n, h, row)[:, :, :w]


def _antidiagonal_transform(f: torch.Tensor, cost: int) -> torch.Tensor:
    """:func:`_line_transform` along the anti-diagonals (``x + y`` constant) of ``(N, H, W)``."""
    w = f.shape[-1]
    return _unskew(_line_transform_cols(_skew(f, float(_INF)), cost), w)


def _forward_pass_rows(d: torch.Tensor) -> None:
    """Forward raster pass of the 3-4 chamfer transform, in place on ``(H, B, W)`` ``int32``.

    Row ``y`` first takes the three neighbours of row ``y - 1`` (vectorised over ``B`` and
    ``W``), then the left neighbour along the row, ``d[x] = min(d[x], d[x - 1] + 3)``, which is
    ``3 x + cummin_k(d[k] - 3 k)``: one cummin instead of a loop over ``x``.
    """
    h, b, w = d.shape
    ramp = torch.arange(w, device=d.device, dtype=d.dtype) * 3
    diag = d.new_empty((b, w - 1))
    up = d.new_empty((b, w))
    vals = d.new_empty((b, w))
    idx = torch.empty((b, w), device=d.device, dtype=torch.int64)
    row = d[0]
    torch.cummin(row - ramp, -1, out=(vals, idx))
    torch.add(vals, ramp, out=row)
    for y in range(1, h):
        prev, row = row, d[y]
        torch.add(prev, 3, out=up)
        torch.minimum(row, up, out=row)
        torch.minimum(prev[:, :-1], prev[:, 1:], out=diag)
        diag += 4
        torch.minimum(row[:, 1:], diag, out=row[:, 1:])  # from (x - 1, y - 1)
        torch.minimum(row[:, :-1], diag, out=row[:, :-1])  # from (x + 1, y - 1)
        row -= ramp
        torch.cummin(row, -1, out=(vals, idx))
        torch.add(vals, ramp, out=row)


def _chamfer_rows(f: torch.Tensor) -> torch.Tensor:
    """The two-pass algorithm itself, rows in sequence: ``(B, H, W) -> (B, H, W)`` ``int32``."""
    d = f.permute(1, 0, 2).contiguous()  # (H, B, W): each row of the batch is one block
    _forward_pass_rows(d)
    d = d.flip(0, 2).contiguous()  # the backward pass is the forward pass on the flipped image
    _forward_pass_rows(d)
    return d.flip(0, 2).permute(1, 0, 2)


def _chamfer_lines(f: torch.Tensor) -> torch.Tensor:
    """Loop-free form (module docstring): ``(B, H, W) -> (B, H, W)`` ``int32``."""
    # float32 holds the integer chamfer values exactly (all stay below 2**22) and its cummin is
    # faster than int32's on CPU.
    f = f.to(torch.float32)
    # Stage 1: runs of diagonal steps (cost 4), along both diagonal families.
    d1 = torch.minimum(_antidiagonal_transform(f, 4), _antidiagonal_transform(f.flip(2), 4).flip(2))
    # Stage 2: one run of axial steps (cost 3) along the row or the column.
    d = torch.minimum(_line_transform(d1, 3), _line_transform_cols(d1, 3))
    return d.to(torch.int32)


# Smallest CPU batch for which "auto" takes the row algorithm (see chamfer_distance_transform).
_ROWS_MIN_BATCH = 3


def chamfer_distance_transform(
    seeds: torch.Tensor, algorithm: Literal["auto", "rows", "lines"] = "auto"
) -> torch.Tensor:
    """Borgefors 3-4 chamfer distance to the nearest seed pixel, in chamfer units.

    The result is exactly that of the classic two-pass algorithm (forward raster pass with the
    neighbours ``(x-1, y-1) +4, (x, y-1) +3, (x+1, y-1) +4, (x-1, y) +3``, then the mirrored
    backward pass). Two implementations give the same integers:

    - ``"rows"``: the two passes, rows in sequence, each row vectorised over the batch and the
      width (``2 H`` small steps; fastest on CPU for batches).
    - ``"lines"``: the loop-free form of the module docstring (a few dozen large operations;
      suited to GPUs, where the per-row launches of ``"rows"`` dominate).
    - ``"auto"``: ``"rows"`` on CPU for batches of 3 images or more,
      ``"lines"`` otherwise (on a 2-core CPU at 720x576, ``"rows"`` costs about 90 ms plus
      3.5 ms per image, ``"lines"`` about 40 ms per image: ``benchmarks/bench_segmentation.py``).

    Args:
        seeds: ``(B, 1, H, W)`` bool, ``True`` on the pixels to measure from (distance 0).
        algorithm: see above.

    Returns:
        ``(B, 1, H, W)`` ``int32``; divide by 3 for pixels. Images without any seed hold
        ``2**20`` everywhere.

    Raises:
        ShapeError: for a wrongly shaped or non-bool ``seeds``.
        ValueError: for an unknown ``algorithm``.
    """
    _check_masks("seeds", seeds)
    if algorithm == "auto":
        on_cpu = seeds.device.type == "cpu"
        algorithm = "rows" if on_cpu and seeds.shape[0] >= _ROWS_MIN_BATCH else "lines"
    f = torch.where(seeds[:, 0], 0, _INF).to(torch.int32)
    if algorithm == "rows":
        d = _chamfer_rows(f)
    elif algorithm == "lines":
        d = _chamfer_lines(f)
    else:
        raise ValueError(
            f"chamfer_distance_transform: algorithm must be 'auto', 'rows' or 'lines', "
            f"got {algorithm!r}"
        )
    return torch.clamp_max(d, _INF).unsqueeze(1)


def euclidean_distance_transform(seeds: torch.Tensor) -> torch.Tensor:
    """Exact Euclidean distance to the nearest seed pixel, in pixels.

    Cost grows with the largest distance in the batch (one vectorised step per pixel of it);
    on CPU the chamfer transform is much faster and is the default of :func:`distance_map`.

    Args:
        seeds: ``(B, 1, H, W)`` bool, ``True`` on the pixels to measure from.

    Returns:
        ``(B, 1, H, W)`` ``float32`` pixels; ``+inf`` in images without any seed.
    """
    _check_masks("seeds", seeds)
    h, w = seeds.shape[-2:]
    if max(h, w) >= _EDT_INF:
        raise ShapeError(f"seeds: expected H, W < {_EDT_INF}, got {tuple(seeds.shape)}")
    # int32 is exact here: squared column distances stay <= 2**30, plus o**2 < 2**30.
    f = torch.where(seeds[:, 0], 0, _EDT_INF).to(torch.int32)
    g = _line_transform_cols(f, 1).clamp_max(_EDT_INF)  # |dv| to the nearest seed in the column
    g2 = g * g
    best = g2.clone()
    has_seed = seeds.flatten(1).any(dim=1)
    if bool(has_seed.any()):
        for o in range(1, w):
            if int(best.amax(dim=(1, 2))[has_seed].max()) <= o * o:
                break  # no pixel can still find a closer seed o or more columns away
            torch.minimum(best[:, :, o:], g2[:, :, :-o] + o * o, out=best[:, :, o:])
            torch.minimum(best[:, :, :-o], g2[:, :, o:] + o * o, out=best[:, :, :-o])
    dist = best.to(torch.float64).sqrt().to(torch.float32)
    dist[~has_seed] = float("inf")
    return dist.unsqueeze(1)


def distance_map(
    seeds: torch.Tensor, method: Literal["chamfer", "euclidean"] = "chamfer"
) -> torch.Tensor:
    """Distance in pixels to the nearest seed pixel.

    Args:
        seeds: ``(B, 1, H, W)`` bool (usually a :func:`contour_mask`).
        method: ``"chamfer"`` (Borgefors 3-4, chamfer value / 3, as in the paper) or
            ``"euclidean"`` (exact).

    Returns:
        ``(B, 1, H, W)`` ``float32`` pixels; ``+inf`` in images without any seed.

    Raises:
        ValueError: for an unknown ``method``.
    """
    if method == "chamfer":
        d = chamfer_distance_transform(seeds)
        out = d.to(torch.float32) / 3.0
        return out.masked_fill(d >= _INF, float("inf"))
    if method == "euclidean":
        return euclidean_distance_transform(seeds)
    raise ValueError(f"distance_map: method must be 'chamfer' or 'euclidean', got {method!r}")


def mask_to_distance_map(
    masks: torch.Tensor, method: Literal["chamfer", "euclidean"] = "chamfer"
) -> torch.Tensor:
    """Distance map of each mask's outer contour (the paper's ``D_P``).

    Args:
        masks: ``(B, 1, H, W)`` bool silhouettes (one region each).
        method: see :func:`distance_map`.

    Returns:
        ``(B, 1, H, W)`` ``float32`` pixels to the nearest outer-contour pixel.
    """
    return distance_map(contour_mask(masks), method)


def sample_distance_map(
    dist: torch.Tensor, points: torch.Tensor, rows: torch.Tensor | None = None
) -> torch.Tensor:
    """Bilinear sample of distance maps at sub-pixel points, differentiable in the points.

    Pixel ``(0, 0)`` is the centre of the top-left pixel, so integer points return the stored
    values exactly. Points outside the image take the value of the nearest border point
    (clamped; the gradient there is zero in the clamped direction). The four neighbours are
    chosen from the detached points, so the result is differentiable in ``points`` in reverse
    and in forward mode (dual tensors), piecewise bilinear with kinks on the pixel grid lines.

    Args:
        dist: ``(B, 1, H, W)`` floating maps (``H, W >= 2``), on the device of ``points``. Their
            dtype may differ from the points': the four neighbours' values are cast to the
            points' dtype before they are blended (float32 maps of whole pixel distances
            sample as float64 maps would, at half the memory).
        points: ``(N, P, 2)`` ``(u, v)`` floating pixels; without ``rows``, ``N = B`` and row
            ``i`` samples map ``i``.
        rows: optional ``(N,)`` integer index of the map each row of ``points`` samples.

    Returns:
        ``(N, P)`` sampled distances, in the points' dtype.

    Raises:
        ShapeError: for wrongly shaped inputs, or maps or points that are not floating.
    """
    check_shape("dist", dist, ("B", 1, "H", "W"))
    if rows is None:
        check_shape("points", points, (dist.shape[0], "N", 2))
        rows = torch.arange(dist.shape[0], device=dist.device)
    else:
        check_shape("points", points, ("N", "P", 2))
        check_shape("rows", rows, (points.shape[0],))
    h, w = dist.shape[-2:]
    if h < 2 or w < 2:
        raise ShapeError(f"dist: expected H, W >= 2 for bilinear sampling, got {tuple(dist.shape)}")
    if not (dist.is_floating_point() and points.is_floating_point()):
        raise ShapeError(
            f"dist, points: expected floating tensors, got {dist.dtype} and {points.dtype}"
        )
    dmap = dist[:, 0]
    u = points[..., 0].clamp(0, w - 1)
    v = points[..., 1].clamp(0, h - 1)
    u0 = u.detach().floor().clamp(max=w - 2)
    v0 = v.detach().floor().clamp(max=h - 2)
    fu, fv = u - u0, v - v0
    u0, v0 = u0.long(), v0.long()
    r = rows[:, None].expand_as(u0)
    at = lambda dv, du: dmap[r, v0 + dv, u0 + du].to(points.dtype)  # noqa: E731
    d00, d01, d10, d11 = at(0, 0), at(0, 1), at(1, 0), at(1, 1)
    return (d00 * (1 - fu) + d01 * fu) * (1 - fv) + (d10 * (1 - fu) + d11 * fu) * fv
