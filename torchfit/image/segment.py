"""The segmentation chain: colour test, optional shadow test, clean-up (first paper, section 4).

Conventions: images ``(B, 3, H, W)`` RGB in ``[0, 1]`` (any float dtype, any device); masks
``(B, 1, H, W)`` bool, ``True`` on the person. :class:`SegmentationOptions` holds every knob
of the chain (it is also the ``segmentation:`` section of the run config).

The chain: with ``photometric`` (default) each frame's per-channel gains against the background
frames are estimated and undone (:mod:`torchfit.image.photometric`: exposure, white balance);
the Mahalanobis test of :mod:`torchfit.image.background` above ``threshold``; with
``shadow_test`` (the default) the foreground pixels :func:`~torchfit.image.shadow.shadow_mask`
takes for a cast shadow, anywhere in the frame (floor, walls, furniture), become background
again (with the optional floor heuristics: only within the lowest ``shadow_band`` of the
foreground, and with ``shadow_bridge`` not between the body and a part cut off below it); then
:func:`clean_mask`:
opening, largest 8-connected region, closing and hole filling; last, with ``edge_width`` (2
by default; 0 turns it off), the outline's mixed pixels that are more background than person become
background (:func:`~torchfit.image.edges.refine_edges`). ``fill_holes`` fills background
regions enclosed by the silhouette; with ``max_hole_area`` only those up to that fraction of
the silhouette's area, so that a large enclosed gap (between the legs, closed below by a shadow
or the feet) stays open. ``plausibility`` holds the bounds that
:func:`~torchfit.image.plausibility.implausible` checks the result against (the pipeline does).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from torchfit.errors import ConfigError, ShapeError
from torchfit.image.background import BackgroundModel, mahalanobis_distance
from torchfit.image.edges import refine_edges
from torchfit.image.morphology import binary_closing, binary_opening, largest_component
from torchfit.image.morphology import fill_holes as _fill_holes
from torchfit.image.photometric import match_background
from torchfit.image.plausibility import PlausibilityOptions
from torchfit.image.shadow import bridged, lower_band, shadow_mask

__all__ = [
    "SegmentationOptions",
    "SegmentationResult",
    "cast_shadow",
    "clean_mask",
    "finish_silhouettes",
    "segment",
]


@dataclass(frozen=True)
class SegmentationOptions:
    """HSL Mahalanobis background subtraction and clean-up (first paper, section 4)."""

    threshold: float = 4.0  # Mahalanobis distance above which a pixel is the person
    gamma: float = 1.0  # weight of lightness against the hue/saturation disc, in [0, 1]
    color_space: Literal["hsl", "rgb"] = "hsl"  # "rgb" is the baseline, for comparisons only
    regularization: float = 1.0  # variance added to the covariance diagonal, (8-bit levels)^2
    min_background_frames: int = 5
    background: Literal["frames", "temporal_median"] = "frames"
    open_kernel: int = 3
    close_kernel: int = 7
    largest_region: bool = True  # keep only the largest region (one person); false keeps all
    # find that region after the closing: a part of the person that the opening cut off (an
    # arm whose link to the body was a thin strip before a background of its own colour)
    # stays when it is within the closing's reach of the body; false takes the largest region
    # of the opened mask (benchmarks/RESULTS.md, "A limb cut off by the opening")
    join_parts: bool = True
    fill_holes: bool = True
    # largest hole filled, as a fraction of the silhouette's area (holes included); None fills
    # every hole. A small value keeps the gap between the legs when a shadow closes it below
    max_hole_area: float | None = None
    # explicit cast-shadow test (the first paper's suggested improvement, its reference [4];
    # image/shadow.py): a foreground pixel that is an attenuated copy of the background is
    # background again. Attenuated: brightness ratio <I, B> / |B|^2 in shadow_ratio; colour
    # distortion at most shadow_chroma (radians) plus shadow_noise standard deviations of the
    # pixel's background noise; where the background is textured (gradient energy at least
    # shadow_min_texture times the noise, over shadow_window x shadow_window pixels), the
    # frame's gradients regress on the background's with a slope of at least shadow_texture
    # times the ratio. No position in the silhouette enters (walls, furniture, floor alike)
    shadow_test: bool = True
    shadow_ratio: tuple[float, float] = (0.3, 1.0)
    shadow_chroma: float = 0.03
    shadow_noise: float = 1.0
    shadow_window: int = 7
    shadow_texture: float = 0.5
    shadow_min_texture: float = 0.5
    shadow_max_residual: float = 10.0
    # where background and frame are both flat (no texture to confirm a shadow: a plain grey
    # shirt in front of a plain lighter grey wall looks like one), call shadow only within the
    # lowest shadow_flat_band fraction of the foreground's height, where the floor shadow lies;
    # 1 everywhere (0.5 chosen on the development data, benchmarks/RESULTS.md)
    shadow_flat_band: float = 0.5
    # floor heuristics (off by default): apply the test only to the lowest shadow_band fraction
    # of the foreground's height (1 applies it everywhere), and keep as person the shadow-like
    # pixels with person both above and below them in their image column (a shin of the
    # floor's colour between the knee and a dark shoe)
    shadow_band: float = 1.0
    shadow_bridge: bool = False
    distance: Literal["chamfer", "euclidean"] = "chamfer"
    # estimate each frame's per-channel gains (exposure, white balance) against the background
    # frames and undo them before the tests (torchfit.image.photometric)
    photometric: bool = True
    # what a silhouette of a standing person can look like (torchfit.image.plausibility);
    # the pipeline fails a subject whose silhouette is not
    plausibility: PlausibilityOptions = field(default_factory=PlausibilityOptions)
    # mixed pixels on the silhouette's outline (the pixel the edge crosses, lens blur, JPEG):
    # within edge_width pixels of the outside, a pixel that is more background than person
    # (its colour as a mix of the background's and a shade of the person's next to it) is
    # background, where the background is edge_separation noise deviations off the person's
    # colour line (torchfit.image.edges); 0: off. The default 2 was chosen on the development
    # sets' segmentation and fit accuracy (benchmarks/RESULTS.md)
    edge_width: int = 2
    edge_separation: float = 6.0
    # run the per-pixel colour test through torch.compile (needs a C++ compiler on CPU; about a
    # minute to compile the first time, cached afterwards; several times faster per frame)
    compile: bool = False

    def __post_init__(self) -> None:
        """Raise :class:`ConfigError` naming the first out-of-range key (a config error stops
        a run before anything is segmented, not each subject)."""

        def bad(name: str, expected: str) -> ConfigError:
            return ConfigError(
                f"segmentation.{name}: expected {expected}, got {getattr(self, name)!r}"
            )

        for name in ("threshold", "shadow_window", "min_background_frames"):
            if not getattr(self, name) > 0:
                raise bad(name, "a number > 0")
        for name in ("regularization", "edge_width", "edge_separation", "shadow_noise"):
            if not getattr(self, name) >= 0:
                raise bad(name, "a number >= 0")
        for name in ("gamma", "shadow_flat_band", "shadow_band", "shadow_texture"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise bad(name, "a number in [0, 1]")
        for name in ("open_kernel", "close_kernel"):
            k = getattr(self, name)
            if k < 0 or (k > 1 and k % 2 == 0):
                raise bad(name, "an odd number of pixels (0 or 1 skips the step)")
        if self.shadow_window % 2 == 0:
            raise bad("shadow_window", "an odd number of pixels")
        ratio = tuple(self.shadow_ratio)
        if len(ratio) != 2 or not 0.0 < ratio[0] <= ratio[1]:
            raise bad("shadow_ratio", "[low, high] with 0 < low <= high")
        if self.max_hole_area is not None and not 0.0 <= self.max_hole_area <= 1.0:
            raise bad("max_hole_area", "a fraction in [0, 1] or null")


def clean_mask(
    masks: torch.Tensor,
    open_kernel: int = 3,
    close_kernel: int = 7,
    fill_holes: bool = True,
    largest_region: bool = True,
    max_hole_area: float | None = None,
    join_parts: bool = True,
) -> torch.Tensor:
    """Opening, largest 8-connected region, closing, optional hole filling (paper, section 4).

    Args:
        masks: ``(B, 1, H, W)`` bool raw foreground.
        open_kernel: side of the square opening element in pixels (odd); ``<= 1`` skips it.
        close_kernel: side of the square closing element (odd); ``<= 1`` skips the closing.
        fill_holes: fill background regions enclosed by the person.
        max_hole_area: with ``fill_holes``, fill only holes up to this fraction (in
            ``[0, 1]``) of the silhouette's area, holes included; None fills every hole.
        largest_region: keep only the largest region (the paper's one-person assumption);
            ``False`` keeps every region that survives the opening (for scenes with several
            people, e.g. for scoring against multi-person ground truth).
        join_parts: with ``largest_region``, find the largest region of the opened mask
            after a closing by ``close_kernel`` and keep the opened pixels in it: the parts
            the opening cut apart stay together when a closing bridges the gap (a forearm
            whose thin link to the body the opening removed); without it, the largest region
            of the opened mask alone.

    Returns:
        ``(B, 1, H, W)`` bool, at most one region per image with ``largest_region`` (empty
        where none was found).
    """
    if not isinstance(masks, torch.Tensor) or masks.dim() != 4 or masks.shape[1] != 1:
        shape = tuple(masks.shape) if isinstance(masks, torch.Tensor) else type(masks).__name__
        raise ShapeError(f"masks: expected shape (B, 1, H, W), got {shape}")
    if masks.dtype != torch.bool:
        raise ShapeError(f"masks: expected a bool tensor, got dtype {masks.dtype}")
    for name, k in (("open_kernel", open_kernel), ("close_kernel", close_kernel)):
        if k > 1 and k % 2 == 0:
            raise ValueError(f"{name} must be odd (or <= 1 to skip the step), got {k}")
    if max_hole_area is not None and not 0.0 <= max_hole_area <= 1.0:
        raise ValueError(f"max_hole_area must be in [0, 1] or None, got {max_hole_area}")
    out = masks
    if open_kernel > 1:
        out = binary_opening(out, open_kernel)
    if largest_region:
        joined = binary_closing(out, close_kernel) if join_parts and close_kernel > 1 else out
        host = joined[:, 0].cpu().numpy()
        kept = torch.from_numpy(np.stack([largest_component(m) for m in host]))
        out = out & kept.to(masks.device).unsqueeze(1)
    if close_kernel > 1:
        out = binary_closing(out, close_kernel)
    if fill_holes:
        host = out[:, 0].cpu().numpy()
        # the closing can join a stray blob to the person: keep the largest region again
        if largest_region:
            host = [largest_component(m) for m in host]
        filled = np.stack([_fill_holes(m, max_hole_area) for m in host])
        out = torch.from_numpy(filled).to(masks.device).unsqueeze(1)
    return out


@dataclass
class SegmentationResult:
    """The output of :func:`segment`.

    Attributes:
        masks: ``(B, 1, H, W)`` bool cleaned silhouettes.
        distance: ``(B, 1, H, W)`` Mahalanobis distance to the background.
        found: ``(B,)`` bool, ``False`` where no person region was left after clean-up.
        shadow: ``(B, 1, H, W)`` bool, the pixels that differ from the background but that the
            shadow test took for a cast shadow (all ``False`` without ``shadow_test``); only
            pixels that the clean-up's opening keeps are decided, isolated noise pixels are
            not marked. Parts
            of the person that look like a darker copy of the floor (grey trousers or shoes on
            a grey or brown floor) end up here too: the fit can treat these pixels as
            uncertain instead of as background (``fit.ignore_shadow``).
        gains: ``(B, 3)`` the per-channel gains undone before the tests (``photometric``),
            1 where none was (none estimated, or one the test would not notice); None
            without ``photometric``.
        tested: ``(B, 3, H, W)`` the images as the tests saw them (the gains undone), which
            :func:`finish_silhouettes` refines the outline against.
    """

    masks: torch.Tensor
    distance: torch.Tensor
    found: torch.Tensor
    shadow: torch.Tensor | None = None
    gains: torch.Tensor | None = None
    tested: torch.Tensor | None = None


def segment(
    images: torch.Tensor,
    background: BackgroundModel,
    options: SegmentationOptions | None = None,
) -> SegmentationResult:
    """Segment the person in a batch of images: Mahalanobis test, then :func:`clean_mask`.

    Args:
        images: ``(B, 3, H, W)`` RGB in ``[0, 1]``.
        background: from :func:`~torchfit.image.background.fit_background`, batch 1 or
            ``B``.
        options: ``threshold``, ``open_kernel``, ``close_kernel``, ``fill_holes``,
            ``max_hole_area``, ``largest_region`` and, with ``shadow_test``, the ``shadow_*``
            keys are used; with ``photometric`` each image's exposure and white balance are
            matched to the background's first
            (:func:`~torchfit.image.photometric.match_background`).

    Returns:
        :class:`SegmentationResult`; an image without a person has ``found = False`` and an
        empty mask (no exception, so one bad image does not stop a batch).
    """
    options = options or SegmentationOptions()
    gains = None
    if options.photometric:
        images, photometric = match_background(images, background, options.threshold)
        gains = photometric.undone
    distance = mahalanobis_distance(background, images, compiled=options.compile)
    raw = distance > options.threshold
    removed = cast_shadow(background, images, raw, options)
    masks = finish_silhouettes(images, background, raw & ~removed, options)
    return SegmentationResult(masks, distance, masks.flatten(1).any(1), removed, gains, images)


def finish_silhouettes(
    tested: torch.Tensor,
    background: BackgroundModel,
    foreground: torch.Tensor,
    options: SegmentationOptions,
) -> torch.Tensor:
    """The chain after its tests: :func:`clean_mask` of the ``foreground`` (B, 1, H, W) the
    tests left, then, with ``edge_width``, the outline's mixed pixels against the images as
    the tests saw them (``tested``, :attr:`SegmentationResult.tested`). :func:`segment` ends
    with it; a caller that gives back some of the pixels the tests removed (the shadow test's,
    :func:`~torchfit.image.shadow.bridged`) finishes its own foreground without testing the
    images again.

    Returns:
        (B, 1, H, W) bool silhouettes.
    """
    masks = clean_mask(
        foreground,
        options.open_kernel,
        options.close_kernel,
        options.fill_holes,
        options.largest_region,
        options.max_hole_area,
        options.join_parts,
    )
    if options.edge_width < 0:
        raise ConfigError(f"segmentation.edge_width: expected >= 0, got {options.edge_width}")
    if options.edge_width > 0:
        masks = refine_edges(
            tested,
            background,
            masks,
            options.edge_width,
            options.edge_separation,
            options.largest_region,
        )
    return masks


def cast_shadow(
    background: BackgroundModel,
    images: torch.Tensor,
    raw: torch.Tensor,
    options: SegmentationOptions,
) -> torch.Tensor:
    """The pixels of the colour test's foreground ``raw`` (B, 1, H, W) that the shadow test of
    ``options`` takes for a cast shadow (all False without ``shadow_test``); ``images`` are
    the (photometrically matched) frames."""
    if not options.shadow_test:
        return torch.zeros_like(raw)
    if len(options.shadow_ratio) != 2:
        raise ConfigError(
            f"segmentation.shadow_ratio: expected [low, high], got {options.shadow_ratio}"
        )
    low, high = options.shadow_ratio[0], options.shadow_ratio[1]
    if not 0.0 < options.shadow_flat_band <= 1.0:
        raise ConfigError(
            "segmentation.shadow_flat_band: expected a value in (0, 1], got "
            f"{options.shadow_flat_band}"
        )
    # the clean-up opens the mask first: what the opening removes is background whatever the
    # shadow test says, so the test decides only inside the box of what the opening keeps
    opened = binary_opening(raw, options.open_kernel) if options.open_kernel > 1 else raw
    flat_band = None
    if options.shadow_flat_band < 1.0:
        flat_band = lower_band(opened, options.shadow_flat_band, 1)
    shadow = shadow_mask(
        background,
        images,
        (low, high),
        options.shadow_chroma,
        options.shadow_noise,
        options.shadow_window,
        options.shadow_texture,
        options.shadow_min_texture,
        options.shadow_max_residual,
        raw,
        flat_band,
        opened,
    )
    if not 0.0 < options.shadow_band <= 1.0:
        raise ConfigError(
            f"segmentation.shadow_band: expected a value in (0, 1], got {options.shadow_band}"
        )
    if options.shadow_band < 1.0:
        shadow = shadow & lower_band(opened, options.shadow_band, 1)
    if options.shadow_bridge:
        shadow = shadow & ~bridged(raw & ~shadow, options.open_kernel)
    return raw & shadow
