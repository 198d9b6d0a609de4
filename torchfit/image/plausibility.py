"""Could this silhouette be a person standing in one of the six postures? Reject what cannot.

Conventions: masks ``(B, 1, H, W)`` bool, ``True`` on the person; the image frames the whole
body (``docs/design.md`` sections 3-4). Fractions are of the image's area; the bounding box
is the smallest axis-aligned box around the mask's pixels, its aspect ``height / width`` in
pixels.

A segmentation can fail without leaving the silhouette empty: a frame much brighter or darker
than the background frames, a black or white frame, a camera that moved, a light switched on,
all turn most of the image into "person". Fitting such a silhouette gives a body metres tall.
:func:`implausible` names, per image, what no person in the postures of design.md section 4
can look like, with bounds (:class:`PlausibilityOptions`) wide enough for all six postures and
for bodies from a child to a tall, heavy adult:

- area: at least ``min_area`` of the image (a speck is noise, not a person) and at most
  ``max_area`` (a standing body that the image frames whole, arms spread, covers about a third
  of the image at the very most);
- borders: the person stands inside the image, so the silhouette touches at most
  ``max_borders`` of the four image borders (feet cut by the bottom border and a hand by a
  side border is already a poor framing; three or four borders is the whole image);
- bounding box aspect ``height / width`` within ``aspect``: about 1 in the T-pose (arm span
  equals height), 1.3-2 in the straddle and side-knee postures, 3-7 standing, side view;
- fill, the mask's share of its bounding box, within ``fill``: about 0.2 in the T-pose (thin
  arms across an empty box), 0.5-0.7 standing; a full rectangle (1) is no body.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchfit.errors import ShapeError

__all__ = ["PlausibilityOptions", "silhouette_shape", "implausible", "cut_borders"]


@dataclass(frozen=True)
class PlausibilityOptions:
    """What a silhouette of a person in one of the six postures can look like."""

    enabled: bool = True  # false: accept any non-empty silhouette
    min_area: float = 0.002  # least share of the image the silhouette covers
    max_area: float = 0.5  # largest share of the image
    max_borders: int = 2  # most image borders (of 4) the silhouette may touch
    aspect: tuple[float, float] = (0.5, 10.0)  # bounding box height / width, pixels
    fill: tuple[float, float] = (0.08, 0.9)  # silhouette area / bounding box area


def silhouette_shape(masks: torch.Tensor) -> dict[str, torch.Tensor]:
    """Area, bounding box and border contacts of each mask.

    Args:
        masks: ``(B, 1, H, W)`` bool.

    Returns:
        ``(B,)`` tensors: ``area`` (share of the image), ``aspect`` (bounding box height /
        width, 0 for an empty mask), ``fill`` (area / bounding box area, 0 when empty) and
        ``borders`` (number of image borders touched, 0-4); ``(B, 4)`` bool ``touches``
        (top, bottom, left, right).

    Raises:
        ShapeError: for anything but a ``(B, 1, H, W)`` bool tensor.
    """
    if not isinstance(masks, torch.Tensor) or masks.dim() != 4 or masks.shape[1] != 1:
        shape = tuple(masks.shape) if isinstance(masks, torch.Tensor) else type(masks).__name__
        raise ShapeError(f"masks: expected shape (B, 1, H, W), got {shape}")
    if masks.dtype != torch.bool:
        raise ShapeError(f"masks: expected a bool tensor, got dtype {masks.dtype}")
    m = masks[:, 0]
    h, w = m.shape[-2:]
    count = m.flatten(1).sum(1).double()
    rows, cols = m.any(2), m.any(1)  # (B, H), (B, W)
    height = _extent(rows).double()
    width = _extent(cols).double()
    touches = torch.stack([rows[:, 0], rows[:, -1], cols[:, 0], cols[:, -1]], 1)
    box = (height * width).clamp_min(1)
    return {
        "area": count / (h * w),
        "aspect": torch.where(width > 0, height / width.clamp_min(1), 0.0),
        "fill": torch.where(count > 0, count / box, 0.0),
        "borders": touches.sum(1),
        "touches": touches,
    }


#: the image borders in :func:`silhouette_shape`'s ``touches`` order
BORDERS = ("top", "bottom", "left", "right")


def cut_borders(masks: torch.Tensor) -> list[list[str]]:
    """The image borders (:data:`BORDERS` names) that cut each ``(B, 1, H, W)`` bool mask:
    the silhouette goes on beyond the picture there (a hand, the feet)."""
    touches = silhouette_shape(masks)["touches"].tolist()
    return [[b for b, t in zip(BORDERS, row, strict=True) if t] for row in touches]


def _extent(any_along: torch.Tensor) -> torch.Tensor:
    """``(B,)`` number of pixels from the first to the last ``True`` of each ``(B, N)`` row."""
    n = any_along.shape[1]
    idx = torch.arange(n, device=any_along.device).expand_as(any_along)
    first = torch.where(any_along, idx, n).amin(1)
    last = torch.where(any_along, idx, -1).amax(1)
    return (last - first + 1).clamp_min(0)


def implausible(
    masks: torch.Tensor, options: PlausibilityOptions | None = None
) -> list[str | None]:
    """Why each silhouette cannot be a person in one of the postures (see the module docstring).

    Args:
        masks: ``(B, 1, H, W)`` bool cleaned silhouettes.
        options: the bounds; defaults to ``PlausibilityOptions()``. With ``enabled`` false
            only an empty silhouette is rejected.

    Returns:
        Per image, None when plausible, else the reasons, e.g. ``"it covers 100 % of the image
        (at most 50 %); it touches 4 image borders (top, bottom, left, right; at most 2)"``.

    Raises:
        ShapeError: for anything but a ``(B, 1, H, W)`` bool tensor.
        ValueError: for bounds that are not ordered.
    """
    options = options or PlausibilityOptions()
    for name in ("aspect", "fill"):
        low, high = getattr(options, name)
        if not 0.0 <= low <= high:
            raise ValueError(f"options.{name} must satisfy 0 <= low <= high, got {(low, high)}")
    shape = silhouette_shape(masks)
    out: list[str | None] = []
    sides = ("top", "bottom", "left", "right")
    for i in range(masks.shape[0]):
        area = float(shape["area"][i])
        if area == 0.0:
            out.append("the silhouette is empty")
            continue
        if not options.enabled:
            out.append(None)
            continue
        why = []
        if area < options.min_area:
            why.append(
                f"it covers {100 * area:.2g} % of the image (at least {_pct(options.min_area)})"
            )
        if area > options.max_area:
            why.append(
                f"it covers {100 * area:.0f} % of the image (at most {_pct(options.max_area)})"
            )
        borders = int(shape["borders"][i])
        if borders > options.max_borders:
            touched = ", ".join(
                s for s, t in zip(sides, shape["touches"][i].tolist(), strict=True) if t
            )
            why.append(
                f"it touches {borders} image borders ({touched}; at most {options.max_borders})"
            )
        aspect = float(shape["aspect"][i])
        if not options.aspect[0] <= aspect <= options.aspect[1]:
            why.append(
                f"its bounding box is {aspect:.2f} times as high as wide "
                f"(a body: {options.aspect[0]:g} to {options.aspect[1]:g})"
            )
        fill = float(shape["fill"][i])
        if not options.fill[0] <= fill <= options.fill[1]:
            why.append(
                f"it fills {100 * fill:.0f} % of its bounding box "
                f"(a body: {_pct(options.fill[0])} to {_pct(options.fill[1])})"
            )
        out.append("; ".join(why) or None)
    return out


def _pct(x: float) -> str:
    return f"{100 * x:.3g} %"
