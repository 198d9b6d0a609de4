"""Options of the fitting problem (:class:`FitOptions`), and the camera's scale at the person
that the image residuals are measured against (:func:`pixels_per_metre`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from torchfit.camera import Camera, camera_centre
from torchfit.errors import ConfigError

__all__ = ["FitOptions", "pixels_per_metre", "image_scale"]


@dataclass(frozen=True)
class FitOptions:
    """Options of the fitting problem (first paper, sections 6–8).

    Attributes:
        poses: the fitted postures (1..6), in order.
        free_joints: per-posture free joint DOFs, e.g. ``{"pose3": ["l_knee_flexion", ...]}``;
            a posture not named keeps the defaults of design.md section 4
            (:data:`torchfit.fit.pose.DEFAULT_FREE_JOINTS`).
        translation_max_m: floor translation interval, each axis, metres.
        yaw_max_deg: yaw interval around the nominal view, degrees.
        tilt_max_deg: roll / pitch interval, degrees.
        side_roll_max_deg: roll interval in the side views (postures 3 and 6), degrees;
            ``None``: ``tilt_max_deg``. Seen from the side, a roll leans the body towards or
            away from the camera: the silhouette hardly shows it, and a fit left free there
            lifts one hip and lowers the other (a longer thigh on the flexed leg of posture 3,
            a shorter shank on the standing one).
        barrier_weight: e_B slope outside an interval.
        samples_per_edge: model contour candidates per mesh edge.
        contour_tolerance_px: a sample within this of the rendered contour is on it.
        contour_stride: use every n-th person contour pixel in e_P.
        contour_orientation_px: pair each person contour pixel (e_P) with the nearest model
            contour sample in ``(u, v, λ n)``, ``λ`` this many pixels and ``n`` the outward
            normals of the pixel and of the sample's edge: a sample facing the other way counts
            ``2 λ`` pixels further off (:mod:`torchfit.fit.model_contour`); in reference
            pixels (``reference_px_per_m``). 0: the nearest sample whichever way it faces.
        ignore_shadow: treat the pixels the segmentation's shadow test removed as uncertain
            rather than as background: no e_P from person contour pixels within
            ``shadow_margin_px`` of them, no e_M from model contour points on them (has an
            effect only where the segmentation ran its shadow test).
        shadow_margin_px: see ``ignore_shadow``.
        pose_outlier_k: a posture whose contour RMS (e_P) exceeds the median of the subject's
            postures by more than ``pose_outlier_k`` robust standard deviations
            (1.4826 MAD, at least ``pose_outlier_min_px``) disagrees with the others: the
            pipeline down-weights it, runs the last stage again and reports it. ``None``: never.
        pose_outlier_min_px: the smallest excess over the median that makes an outlier, pixels.
        pose_outlier_weight: the weight of a down-weighted posture's residuals (its cost
            counts ``pose_outlier_weight²``).
        reference_px_per_m: measure the image residuals (e_P, e_M and the knees' marks) in
            pixels of a camera that sees this many pixels per metre at the person
            (:func:`pixels_per_metre`): each subject's are multiplied by
            ``reference_px_per_m / pixels_per_metre(camera)``, so that the weights of the
            priors and barriers against the images, the robust loss's scale and the
            pipeline's pixel limits mean the same on any camera. ``None``: the image's own
            pixels.
        pixel_noise_ratio: ``ρ``, the contour error's part of a fixed size in the image's
            pixels (the outline's pixels, the segmentation's edge) over its part of a fixed
            size in metres (the template's shape against the body's), at the reference camera.
            With it the image residuals are multiplied by ``sqrt((ρ² + 1) / (ρ² + (p /
            reference_px_per_m)²))`` (``p`` the camera's :func:`pixels_per_metre`) instead:
            between reference pixels (``ρ`` = 0) and the image's own (``ρ`` large), the same
            at the reference camera. ``None``: reference pixels alone.
    """

    poses: tuple[int, ...] = (1, 2, 3, 4, 5, 6)
    free_joints: dict[str, list[str]] | None = None
    translation_max_m: float = 0.15
    yaw_max_deg: float = 15.0
    tilt_max_deg: float = 5.0
    side_roll_max_deg: float | None = None
    barrier_weight: float = 100.0
    samples_per_edge: int = 4
    contour_tolerance_px: float = 1.0
    contour_stride: int = 1
    contour_orientation_px: float = 0.0
    ignore_shadow: bool = True
    shadow_margin_px: int = 2
    pose_outlier_k: float | None = 5.0
    pose_outlier_min_px: float = 3.0
    pose_outlier_weight: float = 0.1
    reference_px_per_m: float | None = None
    pixel_noise_ratio: float | None = None

    def __post_init__(self) -> None:
        ref = self.reference_px_per_m
        if ref is not None and not (math.isfinite(ref) and ref > 0):
            raise ConfigError(f"fit.reference_px_per_m: expected a number > 0 or null, got {ref!r}")
        rho = self.pixel_noise_ratio
        if rho is not None and not (math.isfinite(rho) and rho >= 0):
            raise ConfigError(f"fit.pixel_noise_ratio: expected a number >= 0 or null, got {rho!r}")
        for name, low in _LOWEST.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not (math.isfinite(value) and value >= low):
                raise ConfigError(f"fit.{name}: expected a number >= {low}, got {value!r}")
        if self.pose_outlier_k is not None and not self.pose_outlier_k > 0:
            raise ConfigError(
                f"fit.pose_outlier_k: expected a number > 0 or null, got {self.pose_outlier_k!r}"
            )
        poses = list(self.poses)
        if not poses or len(set(poses)) != len(poses) or not set(poses) <= set(range(1, 7)):
            raise ConfigError(f"fit.poses: expected distinct postures from 1..6, got {poses}")
        if self.side_roll_max_deg is not None and not self.side_roll_max_deg >= 0:
            raise ConfigError(
                f"fit.side_roll_max_deg: expected a number >= 0 or null, got "
                f"{self.side_roll_max_deg!r}"
            )
        if not 0 < self.pose_outlier_weight <= 1:
            raise ConfigError(
                f"fit.pose_outlier_weight: expected a number in (0, 1], got "
                f"{self.pose_outlier_weight!r}"
            )


#: the numeric options' least values (a count at least 1, an interval or a margin at least 0)
_LOWEST = {
    "translation_max_m": 0,
    "yaw_max_deg": 0,
    "tilt_max_deg": 0,
    "barrier_weight": 0,
    "samples_per_edge": 1,
    "contour_tolerance_px": 0,
    "contour_stride": 1,
    "contour_orientation_px": 0,
    "shadow_margin_px": 0,
    "pose_outlier_min_px": 0,
}


def pixels_per_metre(camera: Camera) -> torch.Tensor:
    """(B,) how many pixels a metre spans at the person: the mean focal length over the
    distance from the camera centre to the point 1 m above the floor mark (the middle of a
    person standing there)."""
    centre = camera_centre(camera.R, camera.t)
    middle = torch.tensor([0.0, 0.0, 1.0], dtype=centre.dtype, device=centre.device)
    focal = 0.5 * (camera.K[:, 0, 0] + camera.K[:, 1, 1])
    return focal / (centre - middle).norm(dim=-1)


def image_scale(
    camera: Camera, reference_px_per_m: float | None, pixel_noise_ratio: float | None = None
) -> torch.Tensor:
    """(B,) the factor of each camera's image residuals: reference pixels per image pixel,
    ``reference_px_per_m /`` :func:`pixels_per_metre`, or ones where ``reference_px_per_m``
    is None (image pixels); with ``pixel_noise_ratio`` ``ρ``, ``sqrt((ρ² + 1) / (ρ² + (p /
    reference_px_per_m)²))`` (see :class:`FitOptions`)."""
    if reference_px_per_m is None:
        return torch.ones(camera.K.shape[0], dtype=camera.K.dtype, device=camera.K.device)
    if pixel_noise_ratio is None:
        return reference_px_per_m / pixels_per_metre(camera)
    rho2 = pixel_noise_ratio**2
    relative = pixels_per_metre(camera) / reference_px_per_m
    return ((rho2 + 1.0) / (rho2 + relative * relative)).sqrt()
