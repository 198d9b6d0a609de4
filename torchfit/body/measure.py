"""Measurements of a (scaled) body model, design.md section 5.

Neutral pose: all joint angles zero, root rotation identity, standing on the floor (the lowest
sole landmark at z = 0). Arm span: T-pose (both ``*_shoulder_abduct`` at 90°, everything else
straight), fingertip landmark to fingertip landmark.
"""

from __future__ import annotations

import math

import torch

from torchfit.body.model import BodyModel
from torchfit.errors import ModelError
from torchfit.measurements import measurements_from_joints

__all__ = ["measure_model", "neutral_joints"]

_LANDMARKS = ("head_top", "l_fingertip", "r_fingertip", "l_sole", "r_sole")


def measure_model(model: BodyModel, scales: torch.Tensor) -> dict[str, torch.Tensor]:
    """Measurements of bodies with the given segment scales.

    Args:
        model: the body model.
        scales: (B, S, 3) per-segment scales.

    Returns:
        measurement key -> (B,) metres (keys of :data:`torchfit.measurements.MEASUREMENT_KEYS`),
        differentiable in ``scales``.

    Raises:
        ModelError: the template lacks the landmarks or shoulder DOFs the definitions need.
    """
    missing = [n for n in _LANDMARKS if n not in model.template.landmarks]
    if missing:
        raise ModelError(f"template {model.template.name!r} lacks landmarks {missing}")
    joints = neutral_joints(model, scales)
    p = model.zeros(scales.shape[0])
    t_angles = p["joint_angles"].clone()
    for side in ("l", "r"):
        t_angles[:, model.dof_index(f"{side}_shoulder_abduct")] = math.radians(90.0)
    tpose = model.joint_positions(
        model(scales, t_angles, p["root_translation"], p["root_rotation"])
    )
    span = torch.linalg.vector_norm(tpose["l_fingertip"] - tpose["r_fingertip"], dim=-1)
    return measurements_from_joints(joints, height=joints["head_top"][:, 2], arm_span=span)


def neutral_joints(model: BodyModel, scales: torch.Tensor) -> dict[str, torch.Tensor]:
    """Joint centres and landmarks of bodies with the given segment scales in the neutral
    pose, standing on the floor (the lower sole landmark at z = 0).

    Args:
        model: the body model (its template has ``l_sole`` and ``r_sole`` landmarks).
        scales: (B, S, 3) per-segment scales.

    Returns:
        name -> (B, 3) world positions, metres, differentiable in ``scales``.
    """
    p = model.zeros(scales.shape[0])
    joints = model.joint_positions(
        model(scales, p["joint_angles"], p["root_translation"], p["root_rotation"])
    )
    floor = torch.minimum(joints["l_sole"][:, 2], joints["r_sole"][:, 2])
    lift = torch.stack([torch.zeros_like(floor), torch.zeros_like(floor), floor], -1)
    return {k: v - lift for k, v in joints.items()}
