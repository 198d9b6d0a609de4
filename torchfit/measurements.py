"""Body measurements (design.md section 5), shared by the fitted model and the ground truth.

All lengths in metres. Joint centres are world coordinates of a body in its neutral pose
(all joint angles zero, standing on the floor z = 0, z up). "back" is the pelvis joint centre
(midpoint of the hip joint centres); "neck" is the base of the neck.
"""

from __future__ import annotations

import torch

from torchfit.errors import ShapeError, check_shape

__all__ = ["MEASUREMENT_KEYS", "JOINT_NAMES", "measurements_from_joints"]

#: Keys of measurements.json / truth.json, in report order.
MEASUREMENT_KEYS: tuple[str, ...] = (
    "height_m",
    "arm_span_m",
    "lower_leg_m",
    "thigh_m",
    "upper_arm_m",
    "forearm_m",
    "shoulder_width_m",
    "trunk_m",
    "upper_back_m",
    "virtual_leg_m",
)

#: Joint names of truth.json ``joints_world`` (design.md section 3).
JOINT_NAMES: tuple[str, ...] = (
    "back",
    "neck",
    "head_top",
    "l_shoulder",
    "r_shoulder",
    "l_elbow",
    "r_elbow",
    "l_wrist",
    "r_wrist",
    "l_hip",
    "r_hip",
    "l_knee",
    "r_knee",
    "l_ankle",
    "r_ankle",
)

# the joints the definitions read (back defaults to the midpoint of the hips)
_NEEDED = tuple(n for n in JOINT_NAMES if n not in ("back", "head_top", "l_ankle", "r_ankle"))


def _dist(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.linalg.vector_norm(a - b, dim=-1)


def measurements_from_joints(
    joints: dict[str, torch.Tensor], height: torch.Tensor, arm_span: torch.Tensor
) -> dict[str, torch.Tensor]:
    """Measurements of design.md section 5 from neutral-pose joint centres.

    Args:
        joints: joint name -> (B, 3) world coordinates in metres, neutral pose, floor at z = 0.
            Needs ``neck``, shoulders, elbows, wrists, hips and knees (L and R); ``back``
            defaults to the midpoint of the hips.
        height: (B,) floor to the top of the head, metres.
        arm_span: (B,) fingertip to fingertip in the T-pose, metres.

    Returns:
        measurement key -> (B,) metres, keys as :data:`MEASUREMENT_KEYS`.

    Raises:
        ShapeError: a joint is missing or a tensor has the wrong shape.
    """
    missing = [n for n in _NEEDED if n not in joints]
    if missing:
        raise ShapeError(f"joints: missing joint centres {missing}")
    batch = joints["neck"].shape[0] if joints["neck"].dim() == 2 else -1
    for name, value in joints.items():
        check_shape(f"joints[{name!r}]", value, (batch, 3))
    check_shape("height", height, (batch,))
    check_shape("arm_span", arm_span, (batch,))
    j = joints
    back = j.get("back", 0.5 * (j["l_hip"] + j["r_hip"]))
    mean_lr = lambda f: 0.5 * (f("l") + f("r"))  # noqa: E731
    return {
        "height_m": height,
        "arm_span_m": arm_span,
        "lower_leg_m": mean_lr(lambda s: j[f"{s}_knee"][:, 2]),
        "thigh_m": mean_lr(lambda s: _dist(j[f"{s}_hip"], j[f"{s}_knee"])),
        "upper_arm_m": mean_lr(lambda s: _dist(j[f"{s}_shoulder"], j[f"{s}_elbow"])),
        "forearm_m": mean_lr(lambda s: _dist(j[f"{s}_elbow"], j[f"{s}_wrist"])),
        "shoulder_width_m": _dist(j["l_shoulder"], j["r_shoulder"]),
        "trunk_m": _dist(back, j["neck"]),
        "upper_back_m": mean_lr(lambda s: _dist(back, j[f"{s}_shoulder"])),
        "virtual_leg_m": back[:, 2],
    }
