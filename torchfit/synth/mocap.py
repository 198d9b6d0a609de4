"""Real motion capture (BVH, or CMU ASF/AMC) retargeted onto an anny body.

:func:`load_mocap` reads a clip into joint trajectories with design.md's names (metres, z
up). :func:`retarget` turns one frame into what :meth:`torchfit.synth.body.AnnyBody.pose`
takes: the torso frame (from the hips and the neck) and the local rotations of the upper
arms, forearms, thighs and shanks, each limb bone pointing where the capture's bone points.
The elbow and the knee stay hinges: the upper arm (thigh) turns about its long axis so that
the forearm (shank) bends in its plane; with a straight limb the twist is the smallest
rotation from the neutral pose. Given the body's neutral foot directions, each foot turns
(smallest rotation from where the shank carries it) until its ankle→toe line points along the
capture's ankle→toe-base line, so a foot standing flat in the capture stands flat on the body.
Spine, neck and wrists keep their neutral pose (the torso moves as one rigid block).

A clip's frames start with its motion: a first frame that is the skeleton's rest pose (the
CMU database's BVH conversions start with a T-pose one frame before the capture, from which
the next frame's limbs jump by more than half a metre) is not kept, so a BVH and the ASF/AMC
of the same trial count the same frames.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchfit.errors import DataError
from torchfit.io.asf import read_asf_amc
from torchfit.io.bvh import read_bvh

__all__ = ["MocapClip", "load_mocap", "retarget", "CMU_METRES"]

#: CMU length unit to metres: (1 / 0.45) inches.
CMU_METRES = (1.0 / 0.45) * 2.54 / 100

#: design.md joint -> (BVH joint of the CMU/cgspeed files, ASF bone whose end it is).
_CMU_JOINTS = {
    "l_hip": ("LeftUpLeg", "lhipjoint"),
    "r_hip": ("RightUpLeg", "rhipjoint"),
    "l_knee": ("LeftLeg", "lfemur"),
    "r_knee": ("RightLeg", "rfemur"),
    "l_ankle": ("LeftFoot", "ltibia"),
    "r_ankle": ("RightFoot", "rtibia"),
    "l_shoulder": ("LeftArm", "lclavicle"),
    "r_shoulder": ("RightArm", "rclavicle"),
    "l_elbow": ("LeftForeArm", "lhumerus"),
    "r_elbow": ("RightForeArm", "rhumerus"),
    "l_wrist": ("LeftHand", "lradius"),
    "r_wrist": ("RightHand", "rradius"),
    "neck": ("Neck1", "thorax"),
    "l_toe": ("LeftToeBase", "lfoot"),
    "r_toe": ("RightToeBase", "rfoot"),
}

log = logging.getLogger(__name__)

#: a first frame is a rest pose, not the motion, where some joint (relative to the hips'
#: midpoint) moves from it to the next frame by more than this many metres and this many
#: times the median of the same move over the following frames (01_01.bvh: 0.65 m against a
#: median of 3 mm; a fast kick at 120 frames a second moves a joint a few centimetres)
_REST_JUMP_M = 0.1
_REST_JUMP_RATIO = 20.0

# file axes (y up) -> world (z up)
_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


@dataclass
class MocapClip:
    """Joint trajectories of a clip.

    Attributes:
        joints: design.md joint name -> (F, 3) world positions, metres, z up (``back`` is
            the midpoint of the hips; ``l_toe`` and ``r_toe`` the bases of the toes).
        frame_time: seconds per frame.
        skipped: leading frames of the file that are not the motion (a rest pose), 0 or 1.
    """

    joints: dict[str, np.ndarray]
    frame_time: float
    skipped: int = 0

    @property
    def num_frames(self) -> int:
        """F, the number of frames."""
        return int(next(iter(self.joints.values())).shape[0])


def load_mocap(path: str | Path, unit: float = CMU_METRES) -> MocapClip:
    """A CMU clip: ``.bvh``, or ``.amc`` (its skeleton: the ``.asf`` named by the part of
    the file name before ``_``, in the same folder, e.g. ``11_01.amc`` -> ``11.asf``).

    Args:
        path: the clip.
        unit: the file's length unit in metres.

    Returns:
        The clip from its first frame of motion (a leading rest pose is not kept, see the
        module's text; :attr:`MocapClip.skipped` counts it).

    Raises:
        DataError: unknown format, a missing file or joint.
    """
    path = Path(path)
    if path.suffix.lower() == ".bvh":
        motion = read_bvh(path)
        missing = [b for b, _ in _CMU_JOINTS.values() if b not in motion.names]
        if missing:
            raise DataError(f"{path}: no joint {missing[0]!r} (CMU joint names expected)")
        world = np.stack([motion.world(f)[0] for f in range(motion.num_frames)])
        index = {n: motion.names.index(b) for n, (b, _) in _CMU_JOINTS.items()}
        frame_time = motion.frame_time
    elif path.suffix.lower() == ".amc":
        asf = path.with_name(path.stem.split("_")[0] + ".asf")
        acclaim = read_asf_amc(asf, path)
        missing = [a for _, a in _CMU_JOINTS.values() if a not in acclaim.names]
        if missing:
            raise DataError(f"{asf}: no bone {missing[0]!r} (CMU bone names expected)")
        world = acclaim.positions
        index = {n: acclaim.names.index(a) for n, (_, a) in _CMU_JOINTS.items()}
        frame_time = 1 / 120  # the CMU captures' rate (AMC files do not store it)
    else:
        raise DataError(f"{path}: motion capture must be .bvh or .amc, got {path.suffix!r}")
    joints = {n: unit * world[:, i] @ _Z_UP.T for n, i in index.items()}
    joints["back"] = 0.5 * (joints["l_hip"] + joints["r_hip"])
    skipped = int(_rest_pose_first(joints))
    if skipped:
        log.info("%s: frame 0 is a rest pose, not the motion: not kept", path.name)
        joints = {n: v[skipped:] for n, v in joints.items()}
    return MocapClip(joints=joints, frame_time=frame_time, skipped=skipped)


def _rest_pose_first(joints: dict[str, np.ndarray], window: int = 120) -> bool:
    """Whether the first frame is a rest pose the motion jumps away from (``_REST_JUMP_*``),
    judged on the moves of the joints relative to the hips' midpoint over ``window`` frames."""
    rel = np.stack([v[: window + 1] - joints["back"][: window + 1] for v in joints.values()], 1)
    if rel.shape[0] < 3:
        return False
    moves = np.linalg.norm(np.diff(rel, axis=0), axis=-1).max(1)  # (frames - 1,)
    return bool(moves[0] > max(_REST_JUMP_M, _REST_JUMP_RATIO * float(np.median(moves[1:]))))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _smallest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit ``a`` to unit ``b``."""
    v = np.cross(a, b)
    s, c = float(np.linalg.norm(v)), float(a @ b)
    if s < 1e-9:
        if c > 0:
            return np.eye(3)
        axis = _unit(np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0]))
        return 2 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
    angle = math.atan2(s, c)
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def torso_frame(joints: dict[str, np.ndarray]) -> np.ndarray:
    """(3, 3) body frame (columns: left, backwards, up) from one frame's hips and neck."""
    x = _unit(joints["l_hip"] - joints["r_hip"])
    up = joints["neck"] - joints["back"]
    z = _unit(up - (up @ x) * x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _hinge(d_upper: np.ndarray, d_lower: np.ndarray, bends_forward: bool) -> np.ndarray:
    """Rotation (body frame) of a limb's upper bone: its -z along ``d_upper``, turned about
    it so that the lower bone lies in its y-z plane on the side it bends to (-y forward
    for the elbow, +y backward for the knee)."""
    z = -d_upper
    neutral_y = _smallest(np.array([0.0, 0.0, -1.0]), d_upper) @ np.array([0.0, 1.0, 0.0])
    side = d_lower - (d_lower @ z) * z
    w = min(float(np.linalg.norm(side)) / math.sin(math.radians(20)), 1.0)
    bent_y = _unit(side) * (-1.0 if bends_forward else 1.0)
    y = w * bent_y + (1 - w) * neutral_y if np.linalg.norm(side) > 1e-9 else neutral_y
    y = _unit(y - (y @ z) * z)
    return np.stack([np.cross(y, z), y, z], axis=1)


def retarget(
    joints: dict[str, np.ndarray], feet: dict[str, np.ndarray] | None = None
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """One frame of a clip as the torso frame and the limbs' local rotations.

    Args:
        joints: design.md joint name -> (3,) world position of one frame.
        feet: ``{"l": (3,), "r": (3,)}`` the body's ankle→toe directions in its neutral pose
            (body frame, :meth:`AnnyBody.foot_directions`); without them the feet keep their
            neutral pose under the shanks.

    Returns:
        (3, 3) torso rotation (body frame to world), and ``{"l_upper_arm", "l_forearm",
        "l_thigh", "l_shank", "r_…"}`` (and ``"l_foot"``, ``"r_foot"`` with ``feet``) -> (3, 3)
        local rotations in the neutral body frame (the ``segments`` argument of
        :meth:`AnnyBody.pose`).
    """
    frame = torso_frame(joints)
    out = {}
    limbs = (
        ("upper_arm", "forearm", "shoulder", "elbow", "wrist", True),
        ("thigh", "shank", "hip", "knee", "ankle", False),
    )
    down = np.array([0.0, 0.0, -1.0])
    for side in ("l", "r"):
        for upper, lower, a, b, c, forward in limbs:
            d_u = _unit(frame.T @ (joints[f"{side}_{b}"] - joints[f"{side}_{a}"]))
            d_l = _unit(frame.T @ (joints[f"{side}_{c}"] - joints[f"{side}_{b}"]))
            q_u = _hinge(d_u, d_l, forward)
            q_l = _smallest(q_u @ down, d_l) @ q_u
            out[f"{side}_{upper}"] = q_u
            out[f"{side}_{lower}"] = q_u.T @ q_l
            if feet is not None and lower == "shank":
                d_f = _unit(frame.T @ (joints[f"{side}_toe"] - joints[f"{side}_ankle"]))
                q_f = _smallest(_unit(q_l @ feet[side]), d_f) @ q_l
                out[f"{side}_foot"] = q_l.T @ q_f
    return frame, out
