"""Background subtraction in Cartesian HSL with a per-pixel Mahalanobis test, and clean-up.

This is the segmentation of the first paper (section 4). Conventions:

- Images are ``(B, 3, H, W)`` RGB in ``[0, 1]`` (any float dtype, any device); masks are
  ``(B, 1, H, W)`` bool, ``True`` on the person.
- **Feature units.** Colours are compared in 8-bit-like units (0–255). In the default
  ``color_space="hsl"`` a pixel with hue ``h`` (radians), lightness ``L`` and saturation ``S``
  (both in ``[0, 1]``, as ``kornia.color.rgb_to_hls`` returns them) becomes

      ``f = 255 * (S cos h, S sin h, gamma * L)``

  i.e. hue and saturation as a point on the colour disc and lightness weighted by ``gamma``
  (``gamma = 0`` ignores brightness). ``color_space="rgb"`` is the **baseline** the paper
  improves on: ``f = 255 * (R, G, B)``.
- **Noise floor.** The background model holds, per pixel, the mean ``mu`` and covariance of
  ``f`` over the background frames plus ``regularization * I`` (default ``1.0``: a standard
  deviation of one 8-bit level in each feature, so a pixel that never changed still tolerates
  quantisation-level noise). A pixel belongs to the person when its Mahalanobis distance
  ``sqrt((f - mu)^T Sigma^-1 (f - mu))`` exceeds ``threshold``.
- **Shadows.** A cast shadow scales R, G and B by about the same factor. Hue is unchanged, and
  HLS saturation ``(max - min) / (max + min)`` is unchanged while ``L < 1/2`` (above it, HLS
  saturation is not scale invariant); only the ``gamma``-weighted lightness moves. So with a
  small ``gamma`` shadows on darker-than-mid-grey surfaces stay background, which the RGB
  baseline cannot do.
- **Explicit shadow test** (``shadow_test``, off by default). The paper notes that shadow
  handling "could be improved by a similarity measure like in [4]" (its reference [4]); this
  is such a measure, in the spirit of brightness/chromaticity-distortion shadow detectors. With
  ``B`` the background's mean RGB and ``I`` the pixel's RGB (both 0–1, as stored, i.e. gamma
  encoded; a uniform darkening stays uniform under the power law), the brightness ratio is
  ``alpha = <I, B> / |B|^2`` and the colour change is the angle between ``I`` and ``B``. A
  pixel the Mahalanobis test calls foreground is background again when
  ``shadow_ratio[0] <= alpha <= shadow_ratio[1]`` and the angle is at most ``shadow_chroma``
  radians: darker, same colour direction. Colour alone cannot tell a shadow from grey
  clothing in front of a lighter grey wall (both are "darker, same direction"), so
  ``shadow_band`` limits the test to the lowest fraction of the foreground's vertical extent,
  where a standing person's floor shadow lies; hence also off by default. A shin in trousers
  of the floor's colour passes the test as well and cuts the feet off the silhouette;
  ``shadow_bridge`` keeps as person every shadow-like pixel that has person (non-shadow
  foreground) both above and below it in its image column, as a shin between the knee and a
  shoe has and a shadow cast on the floor beside, behind or in front of the feet has not.
- **Holes.** ``fill_holes`` fills background regions enclosed by the silhouette; with
  ``max_hole_area`` only those up to that fraction of the silhouette's area, so that a large
  enclosed gap (between the legs, closed below by a shadow or the feet) stays open.
- **Backgrounds without empty frames.** ``method="temporal_median"`` (never a silent default)
  estimates the background from frames that may contain the person: per pixel it takes the
  median feature over the frames, keeps the half of the frames closest to it, and uses their
  mean and covariance (scaled by 2.457, the factor that makes a half-sample covariance of a
  3-D Gaussian consistent, as in the minimum covariance determinant estimator).

Colour conversion is ``kornia.color.rgb_to_hls``; with ``compile: true`` it and the Mahalanobis
test run as one ``torch.compile``-d kernel (the same arithmetic, fused). Opening and closing run
on the input's device as separable boolean operations that equal
``kornia.morphology.opening/closing`` with a square element (the tests check this); connected
components and hole filling run in OpenCV on the CPU, one image at a time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import cv2
import kornia
import numpy as np
import torch

from torchfit.config import SegmentationConfig
from torchfit.errors import ConfigError, SegmentationError, ShapeError

__all__ = [
    "BackgroundModel",
    "SegmentationResult",
    "color_features",
    "fit_background",
    "mahalanobis_distance",
    "shadow_mask",
    "clean_mask",
    "segment",
    "cdnet_counts",
    "precision_recall_f",
]

# Half-sample covariance -> full covariance for a 3-D Gaussian:
# 0.5 / chi2.cdf(chi2.ppf(0.5, 3), 5) (the MCD consistency factor for h = n / 2, p = 3).
_HALF_SAMPLE_CONSISTENCY = 2.4574


def _check_images(name: str, images: torch.Tensor, batch_dims: int) -> None:
    if not isinstance(images, torch.Tensor):
        raise ShapeError(f"{name}: expected a torch.Tensor, got {type(images).__name__}")
    if images.dim() != batch_dims + 3 or images.shape[-3] != 3:
        pattern = ", ".join(["B", "N"][:batch_dims] + ["3", "H", "W"])
        raise ShapeError(f"{name}: expected shape ({pattern}), got {tuple(images.shape)}")
    if not images.is_floating_point():
        raise ShapeError(
            f"{name}: expected a float tensor with values in [0, 1], got {images.dtype}"
        )


def color_features(
    images: torch.Tensor, color_space: Literal["hsl", "rgb"] = "hsl", gamma: float = 0.3
) -> torch.Tensor:
    """The colour features the background test compares, in 8-bit-like units.

    Args:
        images: ``(..., 3, H, W)`` RGB in ``[0, 1]``.
        color_space: ``"hsl"`` (the paper: ``255 (S cos h, S sin h, gamma L)``) or ``"rgb"``
            (baseline: ``255 (R, G, B)``).
        gamma: weight of lightness, in ``[0, 1]`` (``"hsl"`` only).

    Returns:
        ``(..., 3, H, W)`` features, same dtype and device as ``images``.
    """
    if color_space == "rgb":
        return images * 255.0
    if color_space != "hsl":
        raise ValueError(f"color_space must be 'hsl' or 'rgb', got {color_space!r}")
    if not 0.0 <= gamma <= 1.0:
        raise ValueError(f"gamma must be in [0, 1], got {gamma}")
    hls = kornia.color.rgb_to_hls(images)
    hue, light, sat = hls[..., 0, :, :], hls[..., 1, :, :], hls[..., 2, :, :]
    sat = sat * 255.0
    return torch.stack([sat * torch.cos(hue), sat * torch.sin(hue), (255.0 * gamma) * light], -3)


@dataclass
class BackgroundModel:
    """Per-pixel Gaussian model of the empty scene in feature space (see the module docstring).

    Attributes:
        mean: ``(B, 3, H, W)`` mean feature, 8-bit-like units.
        covariance: ``(B, 3, 3, H, W)`` covariance including ``regularization * I``.
        color_space: ``"hsl"`` or ``"rgb"`` (baseline).
        gamma: lightness weight used for the features.
        rgb_mean: ``(B, 3, H, W)`` mean RGB in ``[0, 1]`` of the background (for the shadow
            test), or None.
        precision: ``(B, 6, H, W)`` the inverse covariance, packed as
            ``(p00, p11, p22, p01, p02, p12)``; derived, not an argument.
    """

    mean: torch.Tensor
    covariance: torch.Tensor
    color_space: Literal["hsl", "rgb"] = "hsl"
    gamma: float = 0.3
    rgb_mean: torch.Tensor | None = field(default=None, repr=False)
    precision: torch.Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        inv = torch.linalg.inv(self.covariance.permute(0, 3, 4, 1, 2))  # (B, H, W, 3, 3)
        packed = [inv[..., 0, 0], inv[..., 1, 1], inv[..., 2, 2]]
        packed += [inv[..., 0, 1], inv[..., 0, 2], inv[..., 1, 2]]
        self.precision = torch.stack(packed, 1)

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` of the images the model accepts."""
        return int(self.mean.shape[-1]), int(self.mean.shape[-2])

    def to(self, device: torch.device | str) -> BackgroundModel:
        """The same model on another device."""
        rgb = None if self.rgb_mean is None else self.rgb_mean.to(device)
        return BackgroundModel(
            self.mean.to(device), self.covariance.to(device), self.color_space, self.gamma, rgb
        )


def fit_background(
    frames: torch.Tensor, config: SegmentationConfig | None = None
) -> BackgroundModel:
    """Fit the per-pixel background model from frames of the scene.

    Args:
        frames: ``(N, 3, H, W)`` or ``(B, N, 3, H, W)`` RGB in ``[0, 1]``: ``N`` frames per
            subject (``B`` subjects). With ``config.background == "frames"`` they show the empty
            scene; with ``"temporal_median"`` they may show the person (see the module
            docstring).
        config: ``gamma``, ``color_space`` (``"hsl"``, the paper, or ``"rgb"``, the baseline),
            ``regularization`` (variance added on the covariance diagonal, in 8-bit units
            squared), ``background`` (the method) and ``min_background_frames`` are used;
            defaults to ``SegmentationConfig()``.

    Returns:
        A :class:`BackgroundModel` with batch ``B`` (1 for ``(N, 3, H, W)`` input).

    Raises:
        ShapeError: for a wrongly shaped or non-float ``frames``.
        SegmentationError: for fewer than ``config.min_background_frames`` frames.
    """
    config = config or SegmentationConfig()
    if isinstance(frames, torch.Tensor) and frames.dim() == 4:
        frames = frames.unsqueeze(0)
    _check_images("frames", frames, 2)
    n = frames.shape[1]
    if n < max(config.min_background_frames, 2):
        raise SegmentationError(
            f"frames: expected at least {max(config.min_background_frames, 2)} background "
            f"frames (segmentation.min_background_frames), got {n}"
        )
    if config.regularization <= 0:
        raise ValueError(f"config.regularization must be > 0, got {config.regularization}")
    feats = color_features(frames, config.color_space, config.gamma)  # (B, N, 3, H, W)
    if config.background == "frames":
        rgb_mean = frames.mean(1)
        mean = feats.mean(1)
        dev = feats - mean.unsqueeze(1)
        cov = torch.einsum("bnihw,bnjhw->bijhw", dev, dev) / (n - 1)
    elif config.background == "temporal_median":
        med = feats.median(1).values
        dist = (feats - med.unsqueeze(1)).square().sum(2)  # (B, N, H, W)
        keep = math.ceil(n / 2)
        idx = dist.topk(keep, dim=1, largest=False).indices  # (B, keep, H, W)
        kept = feats.gather(1, idx.unsqueeze(2).expand(-1, -1, 3, -1, -1))
        mean = kept.mean(1)
        dev = kept - mean.unsqueeze(1)
        cov = torch.einsum("bnihw,bnjhw->bijhw", dev, dev) / max(keep - 1, 1)
        cov = cov * _HALF_SAMPLE_CONSISTENCY
        rgb = frames.gather(1, idx.unsqueeze(2).expand(-1, -1, 3, -1, -1))
        rgb_mean = rgb.mean(1)
    else:
        raise ValueError(
            f"config.background must be 'frames' or 'temporal_median', got {config.background!r}"
        )
    eye = torch.eye(3, dtype=cov.dtype, device=cov.device).view(1, 3, 3, 1, 1)
    return BackgroundModel(
        mean, cov + config.regularization * eye, config.color_space, config.gamma, rgb_mean
    )


def mahalanobis_distance(
    model: BackgroundModel, images: torch.Tensor, compiled: bool = False
) -> torch.Tensor:
    """Per-pixel Mahalanobis distance of images to the background model.

    Args:
        model: batch ``B_m`` (1 or ``B``).
        images: ``(B, 3, H, W)`` RGB in ``[0, 1]``, the size of the model.
        compiled: run the test through ``torch.compile`` (same result to rounding; several
            times faster on CPU once compiled, see ``segmentation.compile``).

    Returns:
        ``(B, 1, H, W)`` distances (dimensionless).

    Raises:
        ShapeError: for a wrongly shaped ``images``.
        SegmentationError: if the image size differs from the model's, or the batches differ.
    """
    _check_images("images", images, 1)
    w, h = model.size
    if images.shape[-2:] != (h, w):
        raise SegmentationError(
            f"images: expected size {w}x{h} (WxH) of the background model, "
            f"got {images.shape[-1]}x{images.shape[-2]}"
        )
    bm = model.mean.shape[0]
    if bm not in (1, images.shape[0]):
        raise SegmentationError(
            f"images: batch {images.shape[0]} does not match the background model's batch {bm}"
        )
    kernel = _compiled_distance() if compiled else _distance_kernel
    return kernel(images, model.mean, model.precision, model.color_space, model.gamma)


def _distance_kernel(
    images: torch.Tensor,
    mean: torch.Tensor,
    precision: torch.Tensor,
    color_space: str,
    gamma: float,
) -> torch.Tensor:
    d = color_features(images, color_space, gamma) - mean
    p = precision
    d0, d1, d2 = d[:, 0], d[:, 1], d[:, 2]
    sq = p[:, 0] * d0 * d0 + p[:, 1] * d1 * d1 + p[:, 2] * d2 * d2
    sq = sq + 2.0 * (p[:, 3] * d0 * d1 + p[:, 4] * d0 * d2 + p[:, 5] * d1 * d2)
    return sq.clamp_min(0.0).sqrt().unsqueeze(1)


_COMPILED: dict[str, object] = {}


def _compiled_distance():
    """The per-pixel test (kornia's conversion and the quadratic form) through torch.compile:
    one fused loop instead of some twenty full-image passes. Compiled on first use (needs a C++
    compiler on CPU; about a minute the first time, cached by torch afterwards); recompiled
    for a new image size or batch."""
    if "distance" not in _COMPILED:
        _COMPILED["distance"] = torch.compile(_distance_kernel, dynamic=False)
    return _COMPILED["distance"]


def shadow_mask(
    model: BackgroundModel,
    images: torch.Tensor,
    ratio: tuple[float, float] = (0.5, 0.95),
    max_angle: float = 0.05,
) -> torch.Tensor:
    """Pixels that look like a cast shadow on the background (see the module docstring).

    Args:
        model: with ``rgb_mean`` (from :func:`fit_background`), batch 1 or ``B``.
        images: ``(B, 3, H, W)`` RGB in ``[0, 1]``, the size of the model.
        ratio: ``(low, high)`` bounds of the brightness ratio ``<I, B> / |B|^2``.
        max_angle: largest angle (radians) between the pixel's and the background's RGB.

    Returns:
        ``(B, 1, H, W)`` bool, True where the pixel is a darker copy of the background.

    Raises:
        ShapeError: for a wrongly shaped ``images``.
        SegmentationError: if the model has no ``rgb_mean`` or the sizes differ.
    """
    _check_images("images", images, 1)
    if model.rgb_mean is None:
        raise SegmentationError("model: the shadow test needs rgb_mean (use fit_background)")
    if images.shape[-2:] != model.rgb_mean.shape[-2:]:
        raise SegmentationError(
            f"images: expected size {tuple(model.rgb_mean.shape[-2:])} (HxW) of the background "
            f"model, got {tuple(images.shape[-2:])}"
        )
    low, high = ratio
    if not 0.0 < low <= high:
        raise ValueError(f"ratio must satisfy 0 < low <= high, got {ratio}")
    bg = model.rgb_mean.to(images.dtype)
    dot = (images * bg).sum(1, keepdim=True)
    bb = bg.square().sum(1, keepdim=True).clamp_min(1e-6)
    ii = images.square().sum(1, keepdim=True).clamp_min(1e-6)
    alpha = dot / bb
    cos = (dot / (bb * ii).sqrt()).clamp(-1.0, 1.0)
    return (alpha >= low) & (alpha <= high) & (cos >= math.cos(max_angle))


def _lower_band(masks: torch.Tensor, fraction: float, open_kernel: int) -> torch.Tensor:
    """``(B, 1, H, W)`` bool: the rows in the lowest ``fraction`` of each mask's vertical
    extent (measured after an opening by ``open_kernel``, so that speckles do not count)."""
    opened = _binary_morphology(masks, open_kernel, "opening") if open_kernel > 1 else masks
    rows = opened.any(3, keepdim=True)  # (B, 1, H, 1)
    h = masks.shape[2]
    idx = torch.arange(h, device=masks.device).view(1, 1, h, 1)
    top = torch.where(rows, idx, h).amin(2, keepdim=True)
    bottom = torch.where(rows, idx, -1).amax(2, keepdim=True)
    start = bottom - fraction * (bottom - top).clamp_min(0)
    return (idx >= start).expand_as(masks)


def _bridged(person: torch.Tensor, open_kernel: int) -> torch.Tensor:
    """``(B, 1, H, W)`` bool: pixels with the main ``person`` region somewhere above them in
    their column and another person region (cut off from the main one) somewhere below.

    ``person`` is opened by ``open_kernel`` first, so that speckles do not count. Feet still
    joined to the body do not bridge anything: a shadow between a calf and its own foot (beside
    the ankle) stays shadow.
    """
    solid = _binary_morphology(person, open_kernel, "opening") if open_kernel > 1 else person
    host = solid.cpu().numpy().astype(np.uint8)
    main = np.stack([_largest_region(m) for m in host.reshape(-1, *host.shape[-2:])])
    main = torch.from_numpy(main.reshape(host.shape)).to(person.device)
    cut_off = solid.to(torch.uint8) & (1 - main)
    above = torch.cummax(main, dim=2).values.bool()
    below = torch.cummax(cut_off.flip(2), dim=2).values.flip(2).bool()
    return above & below & ~person


def _largest_region(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected region of a ``(H, W)`` uint8 mask (all zero if none)."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n <= 1:
        return np.zeros_like(mask)
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return (labels == biggest).astype(np.uint8)


def _fill_holes(mask: np.ndarray, max_fraction: float | None) -> np.ndarray:
    """Fill the holes of a ``(H, W)`` uint8 mask, only those up to ``max_fraction`` of the
    filled silhouette's area unless ``max_fraction`` is None.

    A hole is a 4-connected background region the flood from outside the image does not reach
    (the complement connectivity of 8-connected regions).
    """
    padded = np.pad(mask, 1)
    flood = padded.copy()
    cv2.floodFill(flood, None, (0, 0), 1)
    holes = (1 - flood[1:-1, 1:-1]).astype(np.uint8)
    if max_fraction is None:
        return mask | holes
    limit = max_fraction * (int(mask.sum()) + int(holes.sum()))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(holes, connectivity=4)
    small = np.zeros(n, dtype=np.uint8)
    small[1:] = stats[1:, cv2.CC_STAT_AREA] <= limit
    return mask | small[labels]


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
    """Opening or closing of a bool ``(B, 1, H, W)`` mask by a ``k x k`` square (``k`` odd).

    Equal to ``kornia.morphology.opening/closing`` with ``torch.ones(k, k)`` on the float mask
    (checked in the tests), but computed as separable shifted OR/AND of bool tensors: kornia's
    grey-level morphology unfolds ``k * k`` values per pixel, which at 720x576 costs more than
    the rest of the chain; for a flat square on a binary mask the separable form is exact.
    """
    first, second = (False, True) if op == "opening" else (True, False)
    for dilate in (first, second):
        x = _shift_reduce(_shift_reduce(x, k, 2, dilate), k, 3, dilate)
    return x


def clean_mask(
    masks: torch.Tensor,
    open_kernel: int = 3,
    close_kernel: int = 7,
    fill_holes: bool = True,
    largest_region: bool = True,
    max_hole_area: float | None = None,
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
        out = _binary_morphology(out, open_kernel, "opening")
    if largest_region:
        host = out[:, 0].to(torch.uint8).cpu().numpy()
        kept = np.stack([_largest_region(m) for m in host])
        out = torch.from_numpy(kept).to(masks.device).bool().unsqueeze(1)
    if close_kernel > 1:
        out = _binary_morphology(out, close_kernel, "closing")
    if fill_holes:
        host = out[:, 0].to(torch.uint8).cpu().numpy()
        # the closing can join a stray blob to the person: keep the largest region again
        if largest_region:
            host = [_largest_region(m) for m in host]
        filled = np.stack([_fill_holes(m, max_hole_area) for m in host])
        out = torch.from_numpy(filled).to(masks.device).bool().unsqueeze(1)
    return out


@dataclass
class SegmentationResult:
    """The output of :func:`segment`.

    Attributes:
        masks: ``(B, 1, H, W)`` bool cleaned silhouettes.
        distance: ``(B, 1, H, W)`` Mahalanobis distance to the background.
        found: ``(B,)`` bool, ``False`` where no person region was left after clean-up.
        shadow: ``(B, 1, H, W)`` bool, the pixels that differ from the background but that the
            shadow test took for a cast shadow (all ``False`` without ``shadow_test``). Parts
            of the person that look like a darker copy of the floor (grey trousers or shoes on
            a grey or brown floor) end up here too: the fit can treat these pixels as
            uncertain instead of as background (``fit.ignore_shadow``).
    """

    masks: torch.Tensor
    distance: torch.Tensor
    found: torch.Tensor
    shadow: torch.Tensor | None = None


def segment(
    images: torch.Tensor, model: BackgroundModel, config: SegmentationConfig | None = None
) -> SegmentationResult:
    """Segment the person in a batch of images: Mahalanobis test, then :func:`clean_mask`.

    Args:
        images: ``(B, 3, H, W)`` RGB in ``[0, 1]``.
        model: from :func:`fit_background`, batch 1 or ``B``.
        config: ``threshold``, ``open_kernel``, ``close_kernel``, ``fill_holes``,
            ``max_hole_area``, ``largest_region`` and, with ``shadow_test``, ``shadow_ratio``,
            ``shadow_chroma`` and ``shadow_band`` are used.

    Returns:
        :class:`SegmentationResult`; an image without a person has ``found = False`` and an
        empty mask (no exception, so one bad image does not stop a batch).
    """
    config = config or SegmentationConfig()
    distance = mahalanobis_distance(model, images, compiled=config.compile)
    raw = distance > config.threshold
    removed = torch.zeros_like(raw)
    if config.shadow_test:
        if len(config.shadow_ratio) != 2:
            raise ConfigError(
                f"segmentation.shadow_ratio: expected [low, high], got {config.shadow_ratio}"
            )
        shadow = shadow_mask(
            model, images, (config.shadow_ratio[0], config.shadow_ratio[1]), config.shadow_chroma
        )
        if not 0.0 < config.shadow_band <= 1.0:
            raise ConfigError(
                f"segmentation.shadow_band: expected a value in (0, 1], got {config.shadow_band}"
            )
        if config.shadow_band < 1.0:
            shadow = shadow & _lower_band(raw, config.shadow_band, config.open_kernel)
        if config.shadow_bridge:
            shadow = shadow & ~_bridged(raw & ~shadow, config.open_kernel)
        removed = raw & shadow
        raw = raw & ~shadow
    masks = clean_mask(
        raw,
        config.open_kernel,
        config.close_kernel,
        config.fill_holes,
        config.largest_region,
        config.max_hole_area,
    )
    return SegmentationResult(masks, distance, masks.flatten(1).any(1), removed)


def cdnet_counts(pred: np.ndarray | torch.Tensor, labels: np.ndarray) -> dict[str, int]:
    """Pixel counts of a predicted mask against a CDnet-style label image.

    Labels: 255 person; 85 (outside the region of interest) and 170 (unknown band) are ignored;
    everything else (0, 50 = shadow, stray low values) is background.

    Args:
        pred: ``(H, W)`` mask, non-zero = person.
        labels: ``(H, W)`` uint8 ground truth.

    Returns:
        ``tp, fp, fn, tn`` and ``shadow`` (pixels labelled 50) with ``shadow_as_background``
        (of those, predicted background).
    """
    if isinstance(pred, torch.Tensor):
        pred = pred.detach().cpu().numpy()
    pred = np.asarray(pred)
    while pred.ndim > 2 and pred.shape[0] == 1:  # accept (1, H, W) and (1, 1, H, W)
        pred = pred[0]
    pred = pred != 0
    labels = np.asarray(labels)
    if pred.shape != labels.shape:
        raise ShapeError(f"labels: expected shape {pred.shape} of the mask, got {labels.shape}")
    valid = (labels != 85) & (labels != 170)
    fg = labels == 255
    bg = valid & ~fg
    shadow = labels == 50
    return {
        "tp": int((pred & fg).sum()),
        "fp": int((pred & bg).sum()),
        "fn": int((~pred & fg).sum()),
        "tn": int((~pred & bg).sum()),
        "shadow": int(shadow.sum()),
        "shadow_as_background": int((~pred & shadow).sum()),
    }


def precision_recall_f(counts: dict[str, int]) -> tuple[float, float, float]:
    """Precision, recall and F-measure from summed :func:`cdnet_counts` (0 where undefined)."""
    tp, fp, fn = counts["tp"], counts["fp"], counts["fn"]
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return precision, recall, f
