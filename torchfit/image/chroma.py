"""Chroma key: the person in front of a coloured screen (the second paper's segmentation).

Conventions: images ``(B, 3, H, W)`` RGB in ``[0, 1]``; masks ``(B, 1, H, W)`` bool, ``True``
on the person.

The key colour ``K`` is given (:attr:`ChromaKeyOptions.key`, 8-bit RGB) or estimated from the
background frames (:func:`estimate_key`). Its dominant channel ``m`` (green for a green screen)
defines a pixel's *key excess* ``e(C) = C_m - max(other channels)``: the screen has a large
excess, skin, hair and clothes have little or none. A pixel's **keyness** is its excess as a
fraction of the screen's own excess at that pixel (the mean background frame's, where there
are background frames; the key colour's otherwise), so that an unevenly lit screen keys
evenly. A mixed edge pixel with person coverage ``alpha`` has keyness about ``1 - alpha``, so
``tolerance = 0.5`` puts the silhouette's edge where half the pixel is person.

- **Shadows** of the person on the screen lower the excess with the brightness; a pixel whose
  excess *relative to its own brightness* is at least ``1 - shadow_tolerance`` of the screen's
  and whose brightness is at least ``shadow_min`` of the screen's is screen too.
- **Spill** (light reflected from the screen that tints the person's edge): the person's edge
  pixels carry a small key excess. They stay person while it is below ``tolerance``; with
  ``despill`` the colour handed on (:func:`despill`) has the excess removed in a band of
  ``spill_px`` pixels along the silhouette's edge (the dominant channel limited to the largest
  other one), so skin-colour tests on the images (the wrists) do not see a green fringe.

The mask then goes through the same clean-up as background subtraction
(:func:`torchfit.image.segment.clean_mask`, done by the caller).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from torchfit.errors import ConfigError, SegmentationError, ShapeError

__all__ = [
    "ChromaKeyOptions",
    "estimate_key",
    "key_colour",
    "keyness",
    "chroma_key",
    "screen_frame",
    "despill",
]

_EPS = 1e-6


@dataclass(frozen=True)
class ChromaKeyOptions:
    """The ``segmentation.chroma_key`` section.

    Attributes:
        key: the screen's colour as 8-bit RGB ``[r, g, b]``; None estimates it from the
            background frames (then they are needed).
        tolerance: a pixel is screen when its key excess is at least this fraction of the
            screen's (0.5: the edge where half a pixel is person).
        shadow_tolerance: a darker pixel is screen when its excess relative to its brightness
            is within this fraction of the screen's (shadows on the screen).
        shadow_min: ... and its brightness is at least this fraction of the screen's.
        despill: remove the key excess from the posture images along the silhouette's edge.
        spill_px: width of that band, pixels.
        gamma: the frames' encoding gamma, undone before keying (light mixes linearly at the
            silhouette's edge and in the spill; 1 keys the pixel values as they are).
        off_screen: where the background frames show no screen (the studio around it), a
            pixel is person when a channel differs from the frames' mean by more than this
            (in [0, 1]).
    """

    key: tuple[float, float, float] | None = None
    tolerance: float = 0.5
    shadow_tolerance: float = 0.25
    shadow_min: float = 0.25
    despill: bool = True
    spill_px: int = 3
    gamma: float = 1.0
    off_screen: float = 0.12

    def check(self) -> None:
        """Raise :class:`ConfigError` naming the first out-of-range key."""
        if self.key is not None and (
            len(self.key) != 3 or any(not 0 <= v <= 255 for v in self.key)
        ):
            raise ConfigError(
                f"segmentation.chroma_key.key: expected [r, g, b] in 0..255, got {self.key}"
            )
        for name in ("tolerance", "shadow_tolerance", "shadow_min", "off_screen"):
            value = getattr(self, name)
            if not 0.0 < value < 1.0:
                raise ConfigError(
                    f"segmentation.chroma_key.{name}: expected a value in (0, 1), got {value}"
                )
        if not 0.5 <= self.gamma <= 4.0:
            raise ConfigError(
                f"segmentation.chroma_key.gamma: expected a value in [0.5, 4], got {self.gamma}"
            )
        if self.spill_px < 0:
            raise ConfigError(
                f"segmentation.chroma_key.spill_px: expected >= 0 pixels, got {self.spill_px}"
            )


def _check(name: str, images: torch.Tensor) -> None:
    if not isinstance(images, torch.Tensor) or images.dim() != 4 or images.shape[1] != 3:
        shape = tuple(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
        raise ShapeError(f"{name}: expected shape (B, 3, H, W), got {shape}")


def _excess(images: torch.Tensor, channel: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The key excess ``C_m - max(others)`` and ``C_m``, each (B, 1, H, W)."""
    others = [c for c in range(3) if c != channel]
    dominant = images[:, channel : channel + 1]
    return dominant - images[:, others].amax(1, keepdim=True), dominant


def estimate_key(background: torch.Tensor) -> torch.Tensor:
    """The screen's colour from background frames (N, 3, H, W): the median colour of the
    pixels whose dominant channel is the frames' most common dominant channel and whose
    excess is in the upper half of those (the screen, not the floor edge or the studio
    around it).

    Returns:
        (3,) RGB in [0, 1].

    Raises:
        SegmentationError: the frames show no coloured screen (no channel dominates).
    """
    _check("background", background)
    pixels = background.permute(1, 0, 2, 3).reshape(3, -1)
    dominant = pixels.argmax(0)
    channel = int(torch.bincount(dominant, minlength=3).argmax())
    excess, _ = _excess(pixels.T.reshape(-1, 3, 1, 1), channel)
    excess = excess.flatten()
    screen = excess > 0.05
    if int(screen.sum()) < 0.1 * excess.numel():
        raise SegmentationError(
            "chroma key: the background frames show no coloured screen (fewer than 10 % of "
            "the pixels have one dominant channel); give segmentation.chroma_key.key"
        )
    strong = screen & (excess >= excess[screen].median())
    return pixels[:, strong].median(1).values


def keyness(
    images: torch.Tensor, key: torch.Tensor, screen: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """How much each pixel looks like the screen.

    Args:
        images: (B, 3, H, W) RGB in [0, 1].
        key: (3,) the key colour in [0, 1].
        screen: optional (1, 3, H, W) or (B, 3, H, W) the empty screen per pixel (the mean
            background frame); the key colour everywhere when None.

    Returns:
        ``q`` (B, 1, H, W): the key excess over the screen's at that pixel; ``q_rel``: the
        same relative to brightness (the dominant channel), for shadows (both about 1 on the
        screen and at most about 0 on the person); and the brightness (dominant channel) over
        the screen's.
    """
    _check("images", images)
    key = key.to(images)
    channel = int(key.argmax())
    ref = key.view(1, 3, 1, 1) if screen is None else screen.to(images)
    ref_excess, ref_dominant = _excess(ref, channel)
    ref_excess = ref_excess.clamp_min(_EPS)
    excess, dominant = _excess(images, channel)
    q = excess / ref_excess
    q_rel = (excess / dominant.clamp_min(_EPS)) / (ref_excess / ref_dominant.clamp_min(_EPS))
    brightness = dominant / ref_dominant.clamp_min(_EPS)
    return q, q_rel, brightness


def key_colour(
    options: ChromaKeyOptions,
    background: torch.Tensor | None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """The key colour, (3,) RGB in [0, 1]: ``options.key`` when given, else estimated from
    the background frames (:func:`estimate_key`).

    Raises:
        ConfigError: no key colour and no background frames;
        SegmentationError: no screen in the background frames.
    """
    if options.key is not None:
        return torch.tensor(options.key, dtype=dtype, device=device) / 255.0
    if background is not None:
        return estimate_key(background)
    raise ConfigError(
        "segmentation.chroma_key.key is not set and there are no background frames to "
        "estimate the key colour from"
    )


def chroma_key(
    images: torch.Tensor,
    options: ChromaKeyOptions,
    background: torch.Tensor | None = None,
    key: torch.Tensor | None = None,
) -> torch.Tensor:
    """The raw person mask of a chroma-keyed batch (clean it with
    :func:`~torchfit.image.segment.clean_mask`).

    Args:
        images: (B, 3, H, W) RGB in [0, 1].
        options: the key colour (or None: estimated from ``background``) and tolerances.
        background: optional (N, 3, H, W) frames of the empty screen.
        key: optional (3,) key colour already found (:func:`key_colour`).

    Returns:
        (B, 1, H, W) bool, True on the person.

    Raises:
        ConfigError: an option out of range, or no key colour and no background frames;
        SegmentationError: no screen in the background frames.
    """
    options.check()
    _check("images", images)
    if key is None:
        key = key_colour(options, background, images.dtype, images.device)
    key = key.clamp_min(0) ** options.gamma
    images = images.clamp_min(0) ** options.gamma
    if background is not None:
        background = background.clamp_min(0) ** options.gamma
    screen = off_screen = None
    if background is not None:
        _check("background", background)
        mean = background.mean(0, keepdim=True).to(images)
        # where the empty frames show no screen (the studio around it) the key colour stands
        # in for the screen, and a plain difference from the empty frames decides
        q_screen, _, _ = keyness(mean, key)
        on_screen = q_screen > 0.5
        screen = torch.where(on_screen, mean, key.to(mean).view(1, 3, 1, 1))
        moved = (images - mean).abs().amax(1, keepdim=True) > options.off_screen
        off_screen = ~on_screen & moved
    q, q_rel, brightness = keyness(images, key, screen)
    keyed = q >= options.tolerance
    shadow = (q_rel >= 1.0 - options.shadow_tolerance) & (brightness >= options.shadow_min)
    person = ~(keyed | shadow)
    if off_screen is not None:
        person = torch.where(on_screen, person, off_screen)
    return person


def screen_frame(background: torch.Tensor, options: ChromaKeyOptions) -> torch.Tensor:
    """The empty screen's frames (N, 3, H, W) as one frame (1, 3, H, W) that
    :func:`chroma_key` treats as it treats all of them (their mean under its gamma): a long
    sequence keys every frame against it without averaging the frames again."""
    _check("background", background)
    g = options.gamma
    return (background.clamp_min(0) ** g).mean(0, keepdim=True) ** (1.0 / g)


def despill(
    images: torch.Tensor, masks: torch.Tensor, key: torch.Tensor, spill_px: int = 3
) -> torch.Tensor:
    """Remove the key colour's spill from the person's edge.

    Args:
        images: (B, 3, H, W) RGB in [0, 1].
        masks: (B, 1, H, W) bool silhouettes.
        key: (3,) the key colour in [0, 1].
        spill_px: width of the band inside the silhouette's edge that is treated.

    Returns:
        (B, 3, H, W): ``images`` with the dominant channel limited to the largest other
        channel within ``spill_px`` of the edge (unchanged elsewhere).
    """
    _check("images", images)
    if spill_px <= 0:
        return images
    channel = int(key.argmax())
    k = 2 * spill_px + 1
    inside = -F.max_pool2d(-masks.to(images.dtype), k, stride=1, padding=spill_px)
    band = masks & (inside < 0.5)
    others = [c for c in range(3) if c != channel]
    limited = torch.minimum(images[:, channel], images[:, others].amax(1))
    out = images.clone()
    out[:, channel] = torch.where(band[:, 0], limited, images[:, channel])
    return out
