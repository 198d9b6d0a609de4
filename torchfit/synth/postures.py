"""The six postures (design.md section 4) as joint angles, and their rotations.

Joint angles follow MPEG4 BAP semantics, in degrees here (radians inside the rotations):
``shoulder_abduct`` raises the arm sideways, ``shoulder_flexion`` raises it forwards,
``shoulder_twist`` turns the upper arm about its long axis (positive: external rotation, used
by the cactus posture so that flexing the elbow brings the forearm up),
``elbow_flexion`` bends the elbow, ``hip_abduct`` spreads the leg sideways, ``knee_flexion``
bends the knee backwards. All angles are zero in the neutral pose: standing straight, legs
vertical, arms hanging vertically.

Rotations are expressed in the body frame of the neutral pose: x to the body's left, y
backwards, z up (the forward axis is -y). A right-side rotation is the mirror image
(x -> -x) of the left-side one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "FREE_JOINTS",
    "Posture",
    "POSTURES",
    "STEREO_POSTURE",
    "axis_angle",
    "mirror",
    "perturb",
    "segment_rotations",
]

#: Joint angles that every posture sets (per side ``l_``/``r_``) and that real people miss.
FREE_JOINTS: tuple[str, ...] = (
    "shoulder_abduct",
    "shoulder_flexion",
    "elbow_flexion",
    "hip_abduct",
    "knee_flexion",
)


@dataclass(frozen=True)
class Posture:
    """One posture of design.md section 4.

    Attributes:
        index: 1 … 6.
        name: ``stand``, ``straddle``, ….
        side_view: True when the left side faces the camera (body turned 90° to its right).
        angles: nominal joint angles in degrees, ``{"l_shoulder_abduct": 15.0, …}``; a missing
            free joint is 0.
    """

    index: int
    name: str
    side_view: bool
    angles: dict[str, float] = field(default_factory=dict)

    def angle(self, name: str) -> float:
        """The nominal value of ``name`` in degrees (0 when not set)."""
        return float(self.angles.get(name, 0.0))


def _both(**kwargs: float) -> dict[str, float]:
    return {f"{s}_{k}": v for k, v in kwargs.items() for s in ("l", "r")}


POSTURES: tuple[Posture, ...] = (
    Posture(1, "stand", False, _both(shoulder_abduct=15.0)),
    Posture(2, "straddle", False, _both(shoulder_abduct=45.0, hip_abduct=15.0)),
    Posture(3, "side_knee", True, {**_both(shoulder_flexion=90.0), "l_knee_flexion": 90.0}),
    Posture(4, "t_pose", False, _both(shoulder_abduct=90.0, hip_abduct=5.0)),
    Posture(
        5,
        "cactus",
        False,
        _both(shoulder_abduct=90.0, elbow_flexion=90.0, hip_abduct=10.0, shoulder_twist=90.0),
    ),
    Posture(6, "side_stand", True, {}),
)

#: The posture of the stereo pair (design.md section 7).
STEREO_POSTURE = POSTURES[4]


def perturb(posture: Posture, rng: np.random.Generator, max_deg: float) -> dict[str, float]:
    """Nominal angles of ``posture`` with every free joint moved by up to ``±max_deg``.

    Flexions that are nominally zero only move into flexion (no hyperextension).

    Returns:
        joint name -> degrees, for every free joint on both sides (and the twists).
    """
    out = {}
    for side in ("l", "r"):
        for joint in FREE_JOINTS:
            name = f"{side}_{joint}"
            nominal = posture.angle(name)
            delta = rng.uniform(-max_deg, max_deg)
            if joint.endswith("flexion") and joint != "shoulder_flexion" and nominal == 0:
                delta = abs(delta)
            if joint == "hip_abduct" and nominal == 0:
                delta = abs(delta) * 0.5  # feet together: the legs cannot cross much
            out[name] = nominal + delta
        out[f"{side}_shoulder_twist"] = posture.angle(f"{side}_shoulder_twist")
    return out


def axis_angle(axis: tuple[float, float, float], angle: float) -> np.ndarray:
    """(3, 3) rotation about the unit ``axis`` by ``angle`` radians (right-hand rule)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


_MIRROR = np.diag([-1.0, 1.0, 1.0])


def mirror(rotation: np.ndarray) -> np.ndarray:
    """The mirror image (x -> -x) of a left-side rotation, for the right side."""
    return _MIRROR @ rotation @ _MIRROR


def segment_rotations(angles: dict[str, float]) -> dict[str, np.ndarray]:
    """Local rotations of the limb segments for joint angles in degrees.

    Each rotation acts in the neutral body frame and is carried by the parent segment:
    the world rotation of a segment is its parent's times its local rotation.

    Returns:
        ``{"l_upper_arm", "l_forearm", "l_thigh", "l_shank", and r_…}`` -> (3, 3).
    """
    rad = {k: math.radians(v) for k, v in angles.items()}
    out = {}
    for side in ("l", "r"):
        g = rad.get
        # upper arm: twist about its long axis, then flexion (about x), then abduction
        # (about the forward axis -y): arm hanging along -z goes to +x at 90° abduction.
        twist = axis_angle((0, 0, 1), g(f"{side}_shoulder_twist", 0.0))
        flex = axis_angle((1, 0, 0), -g(f"{side}_shoulder_flexion", 0.0))
        abduct = axis_angle((0, 1, 0), -g(f"{side}_shoulder_abduct", 0.0))
        upper_arm = abduct @ flex @ twist
        # the elbow flexes about the upper arm's x axis, bringing the forearm forwards (-y)
        forearm = axis_angle((1, 0, 0), -g(f"{side}_elbow_flexion", 0.0))
        thigh = axis_angle((0, 1, 0), -g(f"{side}_hip_abduct", 0.0))
        # the knee flexes backwards: the shank goes from -z towards +y
        shank = axis_angle((1, 0, 0), g(f"{side}_knee_flexion", 0.0))
        parts = {"upper_arm": upper_arm, "forearm": forearm, "thigh": thigh, "shank": shank}
        for name, rot in parts.items():
            out[f"{side}_{name}"] = rot if side == "l" else mirror(rot)
    return out
