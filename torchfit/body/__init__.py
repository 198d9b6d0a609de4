"""Template body models: URDF skeleton + rigid per-segment meshes, posed and scaled in torch.

Conventions: metres, radians; body frame x forward, y left, z up; world frame z up with the
floor at z = 0. pytorch-kinematics is imported only by :mod:`torchfit.body.kinematics`.
"""

from torchfit.body.measure import measure_model
from torchfit.body.model import BodyModel, BodyOutput, axis_angle_to_matrix
from torchfit.body.postures import (
    POSTURES,
    Posture,
    facing_yaw,
    nominal_joint_angles,
    pose_nominal,
    root_rotation_for,
)
from torchfit.body.template import Template, available_templates, load_template

__all__ = [
    "BodyModel",
    "BodyOutput",
    "axis_angle_to_matrix",
    "measure_model",
    "Template",
    "load_template",
    "available_templates",
    "POSTURES",
    "Posture",
    "nominal_joint_angles",
    "facing_yaw",
    "root_rotation_for",
    "pose_nominal",
]
