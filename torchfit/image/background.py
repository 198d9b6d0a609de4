"""Per-pixel Gaussian background model in Cartesian HSL and its Mahalanobis test.

This is the colour test of the first paper's segmentation (section 4). Conventions:

- Images are ``(B, 3, H, W)`` RGB in ``[0, 1]`` (any float dtype, any device); background
  frames are ``(N, 3, H, W)`` or ``(B, N, 3, H, W)``.
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
  baseline cannot do (the explicit shadow test is :mod:`torchfit.image.shadow`).
- **Backgrounds without empty frames.** ``background="temporal_median"`` (never a silent
  default) estimates the background from frames that may contain the person: per pixel it
  takes the median feature over the frames, keeps the half of the frames closest to it, and
  uses their mean and covariance (scaled by 2.457, the factor that makes a half-sample
  covariance of a 3-D Gaussian consistent, as in the minimum covariance determinant
  estimator).

Colour conversion is ``kornia.color.rgb_to_hls``; with ``compile`` it and the Mahalanobis test
run as one ``torch.compile``-d kernel (the same arithmetic, fused).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import cv2
import kornia
import numpy as np
import torch

from torchfit.errors import SegmentationError, ShapeError

if TYPE_CHECKING:
    from torchfit.image.segment import SegmentationOptions

__all__ = [
    "BackgroundModel",
    "color_features",
    "fit_background",
    "least_background_frames",
    "mahalanobis_distance",
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
    if _opencv_eligible(images):
        return _hsl_features_opencv(images, gamma)
    hls = kornia.color.rgb_to_hls(images)
    hue, light, sat = hls[..., 0, :, :], hls[..., 1, :, :], hls[..., 2, :, :]
    sat = sat * 255.0
    return torch.stack([sat * torch.cos(hue), sat * torch.sin(hue), (255.0 * gamma) * light], -3)


def _opencv_eligible(x: torch.Tensor) -> bool:
    """Whether ``x`` can go through OpenCV: float32 on the CPU, outside autograd and
    torch.compile (OpenCV's colour conversion, box filter and trigonometry are single SIMD
    passes, several times faster than the equivalent chain of torch operations)."""
    return (
        x.device.type == "cpu"
        and x.dtype == torch.float32
        and not (x.requires_grad and torch.is_grad_enabled())
        and not torch.compiler.is_compiling()
    )


def _hsl_features_opencv(images: torch.Tensor, gamma: float) -> torch.Tensor:
    """:func:`color_features` (``"hsl"``) through OpenCV: ``cv2.cvtColor(RGB2HLS)`` (the same
    formulas as kornia's, hue in degrees) and ``cv2.polarToCart`` for ``S (cos h, sin h)``;
    the same features to about 1e-4 of an 8-bit level (``tests/image/test_background.py``)."""
    h, w = images.shape[-2:]
    flat = images.reshape(-1, 3, h, w)
    hwc = flat.permute(0, 2, 3, 1).contiguous().numpy()
    out = torch.empty(flat.shape, dtype=torch.float32)
    dst = out.numpy()
    for i in range(hwc.shape[0]):
        hue, light, sat = cv2.split(cv2.cvtColor(hwc[i], cv2.COLOR_RGB2HLS))
        sat *= 255.0
        cv2.polarToCart(sat, hue, dst[i, 0], dst[i, 1], angleInDegrees=True)
        np.multiply(light, 255.0 * gamma, out=dst[i, 2])
    return out.reshape(images.shape)


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
        rgb_var: ``(B, 1, H, W)`` per-pixel noise variance of the background's RGB (mean over
            the channels, ``[0, 1]`` units squared, smoothed over 5 x 5 pixels so that a few
            frames give a stable estimate), or None; the shadow test scales the colour
            distortion it allows with it.
        precision: ``(B, 6, H, W)`` the inverse covariance, packed as
            ``(p00, p11, p22, p01, p02, p12)``; derived, not an argument.

    The model is not changed after it is made: quantities derived from it alone (the shadow
    test's background gradients, for instance) are computed once, on first use
    (:meth:`cached`).
    """

    mean: torch.Tensor
    covariance: torch.Tensor
    color_space: Literal["hsl", "rgb"] = "hsl"
    gamma: float = 0.3
    rgb_mean: torch.Tensor | None = field(default=None, repr=False)
    rgb_var: torch.Tensor | None = field(default=None, repr=False)
    precision: torch.Tensor = field(init=False, repr=False)
    _cache: dict = field(init=False, repr=False, compare=False, default_factory=dict)

    def __post_init__(self) -> None:
        inv = torch.linalg.inv(self.covariance.permute(0, 3, 4, 1, 2))  # (B, H, W, 3, 3)
        packed = [inv[..., 0, 0], inv[..., 1, 1], inv[..., 2, 2]]
        packed += [inv[..., 0, 1], inv[..., 0, 2], inv[..., 1, 2]]
        self.precision = torch.stack(packed, 1)

    def cached(self, key: object, make):
        """``make(self)``, computed on the first call for ``key`` and kept with the model:
        for quantities that depend on the background alone, not on the frame."""
        if key not in self._cache:
            self._cache[key] = make(self)
        return self._cache[key]

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)`` of the images the model accepts."""
        return int(self.mean.shape[-1]), int(self.mean.shape[-2])

    def to(self, device: torch.device | str) -> BackgroundModel:
        """The same model on another device."""
        rgb = None if self.rgb_mean is None else self.rgb_mean.to(device)
        var = None if self.rgb_var is None else self.rgb_var.to(device)
        return BackgroundModel(
            self.mean.to(device), self.covariance.to(device), self.color_space, self.gamma, rgb, var
        )


def least_background_frames(options) -> int:
    """The fewest background frames :func:`fit_background` accepts with these segmentation
    options (``min_background_frames``, and two for a covariance)."""
    return max(options.min_background_frames, 2)


def fit_background(
    frames: torch.Tensor, options: SegmentationOptions | None = None
) -> BackgroundModel:
    """Fit the per-pixel background model from frames of the scene.

    Args:
        frames: ``(N, 3, H, W)`` or ``(B, N, 3, H, W)`` RGB in ``[0, 1]``: ``N`` frames per
            subject (``B`` subjects). With ``options.background == "frames"`` they show the empty
            scene; with ``"temporal_median"`` they may show the person (see the module
            docstring).
        options: ``gamma``, ``color_space`` (``"hsl"``, the paper, or ``"rgb"``, the baseline),
            ``regularization`` (variance added on the covariance diagonal, in 8-bit units
            squared), ``background`` (the method) and ``min_background_frames`` are used;
            defaults to ``SegmentationOptions()``.

    Returns:
        A :class:`BackgroundModel` with batch ``B`` (1 for ``(N, 3, H, W)`` input).

    Raises:
        ShapeError: for a wrongly shaped or non-float ``frames``.
        SegmentationError: for fewer than ``options.min_background_frames`` frames.
    """
    from torchfit.image.segment import SegmentationOptions  # here: segment imports this module

    options = options or SegmentationOptions()
    if isinstance(frames, torch.Tensor) and frames.dim() == 4:
        frames = frames.unsqueeze(0)
    _check_images("frames", frames, 2)
    n = frames.shape[1]
    least = least_background_frames(options)
    if n < least:
        raise SegmentationError(
            f"frames: expected at least {least} background frames "
            f"(segmentation.min_background_frames), got {n}"
        )
    if options.regularization <= 0:
        raise ValueError(f"options.regularization must be > 0, got {options.regularization}")
    feats = color_features(frames, options.color_space, options.gamma)  # (B, N, 3, H, W)
    if options.background == "frames":
        rgb_mean = frames.mean(1)
        rgb_var = frames.var(1).mean(1, keepdim=True)
        mean = feats.mean(1)
        dev = feats - mean.unsqueeze(1)
        cov = torch.einsum("bnihw,bnjhw->bijhw", dev, dev) / (n - 1)
    elif options.background == "temporal_median":
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
        rgb_var = rgb.var(1).mean(1, keepdim=True) * _HALF_SAMPLE_CONSISTENCY
    else:
        raise ValueError(
            f"options.background must be 'frames' or 'temporal_median', got {options.background!r}"
        )
    eye = torch.eye(3, dtype=cov.dtype, device=cov.device).view(1, 3, 3, 1, 1)
    rgb_var = torch.nn.functional.avg_pool2d(rgb_var, 5, 1, 2, count_include_pad=False)
    return BackgroundModel(
        mean,
        cov + options.regularization * eye,
        options.color_space,
        options.gamma,
        rgb_mean,
        rgb_var,
    )


def mahalanobis_distance(
    model: BackgroundModel, images: torch.Tensor, compiled: bool = False
) -> torch.Tensor:
    """Per-pixel Mahalanobis distance of images to the background model.

    Args:
        model: batch ``B_m`` (1 or ``B``).
        images: ``(B, 3, H, W)`` RGB in ``[0, 1]``, the size of the model.
        compiled: run the test through ``torch.compile`` (same result to rounding; several
            times faster on CPU once compiled, see ``SegmentationOptions.compile``).

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
    if compiled or not _opencv_eligible(images) or images.shape[0] == 1:
        return kernel(images, model.mean, model.precision, model.color_space, model.gamma)
    # one image at a time: its intermediate planes stay in the cache, a batch's do not (about
    # three times faster per frame at batch 8 on CPU)
    out = []
    for i in range(images.shape[0]):
        j = i if bm > 1 else 0
        mean, precision = model.mean[j : j + 1], model.precision[j : j + 1]
        out.append(kernel(images[i : i + 1], mean, precision, model.color_space, model.gamma))
    return torch.cat(out)


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
    if torch.compiler.is_compiling() or d.requires_grad:
        sq = p[:, 0] * d0 * d0 + p[:, 1] * d1 * d1 + p[:, 2] * d2 * d2
        sq = sq + 2.0 * (p[:, 3] * d0 * d1 + p[:, 4] * d0 * d2 + p[:, 5] * d1 * d2)
        return sq.clamp_min(0.0).sqrt().unsqueeze(1)
    # the same quadratic form in place, nested: d0 (p00 d0 + 2 p01 d1 + 2 p02 d2)
    # + d1 (p11 d1 + 2 p12 d2) + p22 d2^2, eleven passes instead of twenty
    sq = p[:, 3] * d1
    sq.addcmul_(p[:, 4], d2).mul_(2.0).addcmul_(p[:, 0], d0).mul_(d0)
    t = p[:, 5] * d2
    t.mul_(2.0).addcmul_(p[:, 1], d1).mul_(d1)
    sq.add_(t).addcmul_(p[:, 2] * d2, d2)
    return sq.clamp_min_(0.0).sqrt_().unsqueeze(1)


_COMPILED: dict[str, object] = {}


def _compiled_distance():
    """The per-pixel test (kornia's conversion and the quadratic form) through torch.compile:
    one fused loop instead of some twenty full-image passes. Compiled on first use (needs a C++
    compiler on CPU; about a minute the first time, cached by torch afterwards); recompiled
    for a new image size or batch."""
    if "distance" not in _COMPILED:
        _COMPILED["distance"] = torch.compile(_distance_kernel, dynamic=False)
    return _COMPILED["distance"]
