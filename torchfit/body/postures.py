"""The six postures of design.md section 4 and how a body is placed for a camera.

Angles in degrees in the tables (MPEG4 BAP names), radians in tensors. "Facing the camera"
means the body's forward axis (+x of the root frame) points horizontally from the floor mark
towards the camera centre; postures 3 and 6 turn the body 90° to its right from there, so its
left side faces the camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from torchfit.errors import ModelError

__all__ = [
    "Posture",
    "POSTURES",
    "nominal_joint_angles",
    "facing_yaw",
    "root_rotation_for",
    "pose_nominal",
]


@dataclass(frozen=True)
class Posture:
    """One of the six capture postures."""

    index: int
    name: str
    turn_deg: float  # extra yaw from "facing the camera" (negative = turned to its right)
    joints_deg: dict[str, float] = field(default_factory=dict)
    description: str = ""


def _both(dof: str, value: float) -> dict[str, float]:
    return {f"l_{dof}": value, f"r_{dof}": value}


POSTURES: tuple[Posture, ...] = (
    Posture(
        1,
        "stand",
        0.0,
        _both("shoulder_abduct", 15.0),
        "facing camera, feet together, arms hanging 15° away from the body",
    ),
    Posture(
        2,
        "straddle",
        0.0,
        {**_both("hip_abduct", 15.0), **_both("shoulder_abduct", 45.0)},
        "facing camera, hips abducted 15° each, shoulders abducted 45°",
    ),
    Posture(
        3,
        "side_knee",
        -90.0,
        {"l_knee_flexion": 90.0, **_both("shoulder_flexion", 90.0)},
        "left side to camera, left knee flexed 90°, arms horizontal forward",
    ),
    Posture(
        4,
        "t_pose",
        0.0,
        {**_both("shoulder_abduct", 90.0), **_both("hip_abduct", 5.0)},
        "facing camera, shoulders abducted 90°, elbows straight, hips abducted 5°",
    ),
    Posture(
        5,
        "cactus",
        0.0,
        {
            **_both("shoulder_abduct", 90.0),
            **_both("shoulder_twisting", 90.0),
            **_both("elbow_flexion", 90.0),
            **_both("hip_abduct", 10.0),
        },
        "facing camera, shoulders abducted 90°, elbows flexed 90° forearms up, hips 10°",
    ),
    Posture(
        6,
        "side_stand",
        -90.0,
        {},
        "left side to camera, standing straight, arms hanging, feet together",
    ),
)


def nominal_joint_angles(
    dof_names: list[str], posture: int | Posture, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """Nominal joint angles of a posture.

    Args:
        dof_names: the model's Q joint DOF names.
        posture: posture number 1..6 or a :class:`Posture`.

    Returns:
        (Q,) radians; DOFs the posture does not mention are 0.

    Raises:
        ModelError: the posture number is unknown or the model lacks a DOF the posture needs.
    """
    if not isinstance(posture, Posture):
        if posture not in range(1, 7):
            raise ModelError(f"posture must be 1..6, got {posture!r}")
        posture = POSTURES[posture - 1]
    angles = torch.zeros(len(dof_names), dtype=dtype)
    for dof, deg in posture.joints_deg.items():
        if dof not in dof_names:
            raise ModelError(f"posture {posture.name!r} needs joint DOF {dof!r}, not in the model")
        angles[dof_names.index(dof)] = math.radians(deg)
    return angles


def facing_yaw(camera_center: torch.Tensor) -> torch.Tensor:
    """Yaw (radians, about world z) that points the body's +x at the camera.

    Args:
        camera_center: (B, 3) camera centres in the world frame.

    Returns:
        (B,) yaw angles.
    """
    return torch.atan2(camera_center[..., 1], camera_center[..., 0])


def root_rotation_for(
    camera_center: torch.Tensor, posture: int | Posture, extra_yaw: torch.Tensor | float = 0.0
) -> torch.Tensor:
    """Axis-angle root rotation (B, 3) placing the body in a posture's view of the camera."""
    if not isinstance(posture, Posture):
        posture = POSTURES[posture - 1]
    yaw = facing_yaw(camera_center) + math.radians(posture.turn_deg) + extra_yaw
    zero = torch.zeros_like(yaw)
    return torch.stack([zero, zero, yaw], dim=-1)


def pose_nominal(
    model,
    scales: torch.Tensor,
    posture: int | Posture,
    camera_center: torch.Tensor,
):
    """Pose bodies at a posture's nominal angles, facing the camera, standing on the floor mark.

    Args:
        model: a :class:`torchfit.body.model.BodyModel`.
        scales: (B, S, 3) segment scales.
        posture: 1..6 or a :class:`Posture`.
        camera_center: (B, 3) or (3,) camera centres, world frame.

    Returns:
        (params, output): the parameter dict (``joint_angles`` (B, Q), ``root_translation``
        (B, 3), ``root_rotation`` (B, 3)) and the posed :class:`BodyOutput`; the root is above
        the origin and the lowest vertex touches z = 0.
    """
    b = scales.shape[0]
    centre = camera_center.to(scales).expand(b, 3)
    angles = nominal_joint_angles(model.dof_names, posture, scales.dtype).to(scales.device)
    params = {
        "joint_angles": angles.expand(b, -1).clone(),
        "root_translation": torch.zeros(b, 3, dtype=scales.dtype, device=scales.device),
        "root_rotation": root_rotation_for(centre, posture),
    }
    out = model(scales, **params)
    params["root_translation"][:, 2] = -out.vertices[..., 2].amin(dim=1)
    return params, model(scales, **params)
