"""Rotation helpers of the body model: Rodrigues' formula, the skew matrix, SO(3)'s left
Jacobian (smooth at zero), and a root rotation's heading and turn about the world's vertical."""

from __future__ import annotations

import torch

__all__ = [
    "axis_angle_to_matrix",
    "cross_matrix",
    "heading",
    "left_jacobian",
    "turn_about_vertical",
]


def cross_matrix(v: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) matrices ``[v]×`` with ``[v]× w = v × w`` of vectors (..., 3)."""
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*v.shape[:-1], 3, 3)


def axis_angle_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula, smooth at zero.

    Args:
        rotvec: (..., 3) axis * angle, radians.

    Returns:
        (..., 3, 3) rotation matrices.
    """
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    small = theta2 < 1e-12
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = safe2.sqrt()
    # sin(t)/t and (1 - cos t)/t^2 with their Taylor series near 0
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / safe2)
    k = cross_matrix(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def left_jacobian(rotvec: torch.Tensor) -> torch.Tensor:
    """(B, 3, 3) left Jacobian of SO(3) at axis-angles (B, 3): ``I + b K + c K²`` with
    ``b = (1 − cos θ)/θ²``, ``c = (θ − sin θ)/θ³`` (Taylor series near 0)."""
    theta2 = (rotvec * rotvec).sum(-1)[:, None, None]
    small = theta2 < 1e-12
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = safe2.sqrt()
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / safe2)
    c = torch.where(small, 1 / 6 - theta2 / 120, (theta - torch.sin(theta)) / (safe2 * theta))
    k = cross_matrix(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(k)
    return eye + b * k + c * (k @ k)


def turn_about_vertical(r: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Axis-angles (B, 3) of ``Rz(angle) Exp(r)`` (``angle`` (B,) radians about the world's
    vertical), by quaternions; of the two axis-angles of a rotation (``θ u`` and
    ``(θ - 2π) u``), the one nearer ``r``."""
    theta = r.norm(dim=1, keepdim=True)
    axis = r / theta.clamp_min(1e-12)
    w1, v1 = torch.cos(theta / 2), torch.sin(theta / 2) * axis
    wz, sz = torch.cos(angle / 2)[:, None], torch.sin(angle / 2)[:, None]
    # (wz, 0, 0, sz) * (w1, v1)
    w = wz * w1 - sz * v1[:, 2:3]
    v = wz * v1 + sz * torch.cat([-v1[:, 1:2], v1[:, 0:1], w1], 1)
    n = v.norm(dim=1, keepdim=True)
    out = 2 * torch.atan2(n, w) * v / n.clamp_min(1e-12)
    alt = out - 2 * torch.pi * v / n.clamp_min(1e-12)  # the same turn the other way round
    closer = (alt - r).norm(dim=1, keepdim=True) < (out - r).norm(dim=1, keepdim=True)
    return torch.where(closer, alt, out)


def heading(r: torch.Tensor) -> torch.Tensor:
    """(B,) the heading (radians about the vertical) of the root frame's x axis (the body's
    left-right axis) under axis-angles ``r`` (B, 3)."""
    m = axis_angle_to_matrix(r)
    return torch.atan2(m[:, 1, 0], m[:, 0, 0])
