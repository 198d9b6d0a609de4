"""Stereo: pixels → viewing rays → midpoint triangulation → the second paper's lengths.

Conventions (design.md section 2): world frame metres, z up, floor z = 0; cameras map world to
camera with ``x_cam = R x_world + t``; pixels ``(u, v)`` with ``v`` down and OpenCV
distortion. Batches are ``B`` first.

The midpoint method (Trucco and Verri, section 7.4, cited by the paper): each pixel defines a
ray from its camera centre; the 3-D point is the middle of the shortest segment between the two
rays. Undistortion inverts OpenCV's model by the same fixed-point iteration
``cv2.undistortPoints`` uses.
"""

from __future__ import annotations

import numpy as np
import torch

from torchfit.camera import Camera, camera_centre, project_points, ray_directions, undistort_pixels
from torchfit.errors import check_shape
from torchfit.parts.errors import PartsError

__all__ = [
    "project_joints",
    "undistort_pixels",
    "pixel_rays",
    "triangulate_midpoint",
    "STEREO_MEASUREMENT_KEYS",
    "stereo_measurements",
]

#: Lengths the stereo method reports (design.md section 5), metres.
STEREO_MEASUREMENT_KEYS: tuple[str, ...] = (
    "trunk_m",
    "upper_back_m",
    "upper_arm_m",
    "forearm_m",
    "virtual_leg_m",
)


def pixel_rays(pixels: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """World-frame viewing rays of pixels.

    Args:
        pixels: (B, N, 2) ``(u, v)`` pixels.
        camera: B cameras (or one, broadcast).

    Returns:
        ``(origins, directions)``: (B, N, 3) camera centres and (B, N, 3) unit directions.
    """
    d_world = ray_directions(pixels, camera)
    d_world = d_world / torch.linalg.vector_norm(d_world, dim=-1, keepdim=True)
    centre = camera_centre(camera.R.to(pixels), camera.t.to(pixels))
    return centre[:, None, :].expand_as(d_world), d_world


def triangulate_midpoint(
    pixels_left: torch.Tensor,
    camera_left: Camera,
    pixels_right: torch.Tensor,
    camera_right: Camera,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Midpoint triangulation of corresponding pixels in two calibrated views.

    Args:
        pixels_left: (B, N, 2) pixels in the left view.
        camera_left: B (or 1) left cameras.
        pixels_right: (B, N, 2) the corresponding pixels in the right view.
        camera_right: B (or 1) right cameras.

    Returns:
        ``(points, gap)``: (B, N, 3) world points, metres, and (B, N) the length of the
        shortest segment between the two rays (metres; a large gap flags a bad
        correspondence). Parallel rays give NaN.

    Raises:
        ShapeError: the pixel tensors differ in shape.
        PartsError: the two cameras share their centre.
    """
    check_shape("pixels_left", pixels_left, ("B", "N", 2))
    check_shape("pixels_right", pixels_right, tuple(pixels_left.shape))
    o1, d1 = pixel_rays(pixels_left, camera_left)
    o2, d2 = pixel_rays(pixels_right, camera_right)
    if bool((torch.linalg.vector_norm(o1 - o2, dim=-1) < 1e-9).any()):
        raise PartsError("camera_left, camera_right: expected two camera centres, got one")
    # Closest points o1 + s d1 and o2 + r d2: solve the 2x2 normal equations.
    w = o1 - o2
    b = (d1 * d2).sum(-1)
    d = (d1 * w).sum(-1)
    e = (d2 * w).sum(-1)
    denom = 1 - b * b  # |d1| = |d2| = 1
    nan = torch.full_like(denom, float("nan"))
    ok = denom > 1e-12
    s = torch.where(ok, (b * e - d) / denom.clamp_min(1e-12), nan)
    r = torch.where(ok, (e - b * d) / denom.clamp_min(1e-12), nan)
    p1 = o1 + s[..., None] * d1
    p2 = o2 + r[..., None] * d2
    return 0.5 * (p1 + p2), torch.linalg.vector_norm(p1 - p2, dim=-1)


def stereo_measurements(joints: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The second paper's lengths from 3-D joints (design.md section 5).

    trunk = back–neck; upper back = back–shoulder (mean L/R); upper arm = shoulder–elbow and
    forearm = elbow–wrist (mean L/R); virtual leg = the back's height above the floor (z = 0).

    Args:
        joints: name -> (B, 3) world points, metres: ``back``, ``neck``, ``l_/r_shoulder``,
            ``l_/r_elbow`` and, for the forearm, ``l_/r_wrist``.

    Returns:
        key of :data:`STEREO_MEASUREMENT_KEYS` -> (B,) metres (``forearm_m`` only with wrists).

    Raises:
        PartsError: a needed joint is missing.
    """
    needed = ("back", "neck", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow")
    missing = [n for n in needed if n not in joints]
    if missing:
        raise PartsError(f"joints: missing {missing}; expected at least {list(needed)}")

    def dist(a: str, b: str) -> torch.Tensor:
        return torch.linalg.vector_norm(joints[a] - joints[b], dim=-1)

    out = {
        "trunk_m": dist("back", "neck"),
        "upper_back_m": 0.5 * (dist("back", "l_shoulder") + dist("back", "r_shoulder")),
        "upper_arm_m": 0.5 * (dist("l_shoulder", "l_elbow") + dist("r_shoulder", "r_elbow")),
    }
    if "l_wrist" in joints and "r_wrist" in joints:
        out["forearm_m"] = 0.5 * (dist("l_elbow", "l_wrist") + dist("r_elbow", "r_wrist"))
    out["virtual_leg_m"] = joints["back"][..., 2]
    return out


def project_joints(joints: dict[str, list[float]], camera: Camera) -> dict[str, np.ndarray]:
    """Pixels ``(2,)`` of named 3-D joints (metres, world frame) in one camera (B = 1), e.g. the
    true ``joints_world["stereo"]`` of a synthetic subject in one of its views."""
    names = list(joints)
    points = torch.tensor([joints[n] for n in names], dtype=torch.float64)[None]
    return dict(zip(names, project_points(points, camera)[0].numpy(), strict=True))
