"""Rotation helpers of the body model: Rodrigues' formula, the skew matrix and SO(3)'s left
Jacobian (smooth at zero)."""

from __future__ import annotations

import torch

__all__ = ["axis_angle_to_matrix", "cross_matrix", "left_jacobian"]


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
