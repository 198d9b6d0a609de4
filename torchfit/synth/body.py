"""Posed ``anny`` bodies: the neutral pose, postures, joint centres and the head top.

``anny`` is imported lazily (the ``synth`` extra). Its full-body model is z up with the body
facing -y and its left on +x, in an A-pose at rest. We pose it with anny's ``world-orient``
parameterisation (each bone's world orientation given directly) so that the rotations of
:mod:`torchfit.synth.postures` apply in the neutral body frame.

Neutral pose: the upper arm, forearm, thigh and shank bones are turned (smallest rotation)
until shoulder→elbow, elbow→wrist, hip→knee and knee→ankle point straight down; every other
bone keeps its rest orientation relative to its parent (so wrists and feet stay straight).

Joint centres (``JOINT_BONES``; each the head of an anny bone, i.e. its joint with the
parent): shoulder = ``upperarm01``, elbow = ``lowerarm01``, wrist = ``wrist``, hip =
``upperleg01``, knee = ``lowerleg01``, ankle = ``foot``, neck (base of the neck) =
``neck01``; ``back`` is the midpoint of the hips; ``head_top`` is the mesh vertex highest in
the neutral pose, followed as the body moves.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torchfit.errors import ModelError
from torchfit.synth.postures import segment_rotations

__all__ = [
    "JOINT_BONES",
    "SEGMENT_BONES",
    "Phenotype",
    "PosedBody",
    "AnnyBody",
    "load_anny",
]

#: torchfit joint name -> anny bone whose head is the joint centre.
JOINT_BONES: dict[str, str] = {
    "neck": "neck01",
    "l_shoulder": "upperarm01.L",
    "r_shoulder": "upperarm01.R",
    "l_elbow": "lowerarm01.L",
    "r_elbow": "lowerarm01.R",
    "l_wrist": "wrist.L",
    "r_wrist": "wrist.R",
    "l_hip": "upperleg01.L",
    "r_hip": "upperleg01.R",
    "l_knee": "lowerleg01.L",
    "r_knee": "lowerleg01.R",
    "l_ankle": "foot.L",
    "r_ankle": "foot.R",
}

#: segment -> (bone rotated, bone at the segment's distal end) per side ("{s}" = L or R).
SEGMENT_BONES: dict[str, tuple[str, str]] = {
    "upper_arm": ("upperarm01.{s}", "lowerarm01.{s}"),
    "forearm": ("lowerarm01.{s}", "wrist.{s}"),
    "thigh": ("upperleg01.{s}", "lowerleg01.{s}"),
    "shank": ("lowerleg01.{s}", "foot.{s}"),
    "foot": ("foot.{s}", "toe3-1.{s}"),
}


#: how to install what :func:`load_anny` needs
SYNTH_INSTALL_HINT = 'install it with `pip install -e ".[synth]"` (or `pip install anny`)'


@functools.lru_cache(maxsize=1)
def load_anny() -> Any:
    """The anny full-body model (built once, about a minute the first time; cached).

    Raises:
        ModelError: anny (the optional ``synth`` extra) is not installed.
    """
    try:
        import anny  # the optional ``synth`` extra
    except ImportError as exc:
        raise ModelError(
            f"the synthetic bodies need anny, which is not installed: {SYNTH_INSTALL_HINT} ({exc})"
        ) from exc
    return anny.Anny()


@dataclass
class Phenotype:
    """anny phenotype parameters, each in [0, 1] (``age`` 2/3 is a young adult, 1 old)."""

    gender: float
    age: float
    muscle: float
    weight: float
    height: float
    proportions: float

    def as_dict(self) -> dict[str, float]:
        """The phenotype values by name."""
        return {k: float(v) for k, v in self.__dict__.items()}


@dataclass
class PosedBody:
    """A body in anny's frame (metres, z up, facing -y), floor not yet at z = 0.

    Attributes:
        vertices: (V, 3) skinned mesh vertices.
        joints: joint name -> (3,) centre (``JOINT_NAMES`` of torchfit.measurements).
    """

    vertices: np.ndarray
    joints: dict[str, np.ndarray]


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction ``a`` to direction ``b``."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    s, c = np.linalg.norm(v), float(a @ b)
    if s < 1e-12:
        return np.eye(3)  # parallel (antiparallel never occurs for limb bones)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
    angle = math.atan2(s, c)
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


class AnnyBody:
    """One anny body (a phenotype) that can be posed.

    Args:
        phenotype: the anny phenotype.
        model: an anny model (default: :func:`load_anny`).
    """

    def __init__(self, phenotype: Phenotype, model: Any = None) -> None:
        self.model = model if model is not None else load_anny()
        self.phenotype = phenotype
        self.labels = list(self.model.bone_labels)
        self.index = {n: i for i, n in enumerate(self.labels)}
        self.parents = [int(p) for p in self.model.bone_parents]
        with torch.no_grad():
            rest = self.model(phenotype_kwargs=self._kwargs())
        self.rest_poses = rest["rest_bone_poses"][0].double().cpu().numpy()  # (J, 4, 4)
        self.head_top_vertex: int | None = None
        self._neutral = self._neutral_rotations()
        neutral = self.pose({})
        self.head_top_vertex = int(np.argmax(neutral.vertices[:, 2]))

    def _kwargs(self) -> dict[str, torch.Tensor]:
        return {
            k: torch.tensor([v], dtype=torch.float64) for k, v in self.phenotype.as_dict().items()
        }

    def _world_rotations(self, local: dict[int, np.ndarray]) -> np.ndarray:
        """(J, 3, 3) world rotations from local ones (identity where absent), parents first."""
        out = np.zeros((len(self.labels), 3, 3))
        for j, p in enumerate(self.parents):  # anny lists parents before children
            own = local.get(j, np.eye(3))
            out[j] = own if p < 0 else out[p] @ own
        return out

    def _heads(self, world: np.ndarray) -> np.ndarray:
        """(J, 3) bone heads when every bone turns by ``world`` about its own head."""
        rest_heads = self.rest_poses[:, :3, 3]
        heads = np.zeros_like(rest_heads)
        for j, p in enumerate(self.parents):
            if p < 0:
                heads[j] = rest_heads[j]
            else:
                heads[j] = heads[p] + world[p] @ (rest_heads[j] - rest_heads[p])
        return heads

    def _neutral_rotations(self) -> dict[int, np.ndarray]:
        """Local rotations turning the rest A-pose into the neutral pose."""
        local: dict[int, np.ndarray] = {}
        down = np.array([0.0, 0.0, -1.0])
        for side in ("L", "R"):
            for seg in ("upper_arm", "forearm", "thigh", "shank"):
                bone, end = (b.format(s=side) for b in SEGMENT_BONES[seg])
                world = self._world_rotations(local)
                heads = self._heads(world)
                j, e = self.index[bone], self.index[end]
                direction = heads[e] - heads[j]
                # world rotation needed, expressed as a local one under the parent
                fix = _rotation_between(direction, down)
                parent_world = world[self.parents[j]]
                local[j] = parent_world.T @ fix @ world[j]
        return local

    def pose(
        self, angles: dict[str, float], segments: dict[str, np.ndarray] | None = None
    ) -> PosedBody:
        """The body in the joint angles ``angles`` (degrees, see torchfit.synth.postures).

        Args:
            angles: joint angles in degrees.
            segments: instead of ``angles``, the limb segments' local rotations directly, as
                :func:`torchfit.synth.postures.segment_rotations` gives them
                (``{"l_upper_arm": (3, 3), …}``; a missing segment keeps its neutral pose).

        Returns:
            A :class:`PosedBody` in anny's frame.
        """
        seg = segment_rotations(angles) if segments is None else segments
        neutral_world = self._world_rotations(self._neutral)
        local: dict[int, np.ndarray] = {}
        # posture rotations act in the neutral frame: Q_c = Q_p P_c, world = Q_c N_c
        posture_local: dict[int, np.ndarray] = {}
        for side, s in (("l", "L"), ("r", "R")):
            for name, (bone, _) in SEGMENT_BONES.items():
                if f"{side}_{name}" in seg:
                    posture_local[self.index[bone.format(s=s)]] = seg[f"{side}_{name}"]
        q = self._world_rotations(posture_local)
        world = q @ neutral_world
        for j, p in enumerate(self.parents):
            local[j] = world[j] if p < 0 else world[p].T @ world[j]
        rest_r = self.rest_poses[:, :3, :3]
        deltas = np.tile(np.eye(4), (len(self.labels), 1, 1))
        deltas[:, :3, :3] = world @ rest_r
        deltas[0, :3, 3] = self.rest_poses[0, :3, 3]
        with torch.no_grad():
            out = self.model(
                pose_parameters=torch.from_numpy(deltas)[None],
                phenotype_kwargs=self._kwargs(),
                pose_parameterization="world-orient",
            )
        vertices = out["vertices"][0].double().cpu().numpy()
        heads = out["bone_poses"][0, :, :3, 3].double().cpu().numpy()
        joints = {name: heads[self.index[bone]].copy() for name, bone in JOINT_BONES.items()}
        joints["back"] = 0.5 * (joints["l_hip"] + joints["r_hip"])
        top = self.head_top_vertex  # None while the constructor looks for it
        joints["head_top"] = vertices[top].copy() if top is not None else vertices[0] * np.nan
        return PosedBody(vertices=vertices, joints=joints)

    def foot_directions(self) -> dict[str, np.ndarray]:
        """``{"l": (3,), "r": (3,)}``: each foot's unit direction from the ankle to the base
        of its middle toe in the neutral pose (body frame)."""
        heads = self._heads(self._world_rotations(self._neutral))
        out = {}
        for side, s in (("l", "L"), ("r", "R")):
            bone, end = (b.format(s=s) for b in SEGMENT_BONES["foot"])
            d = heads[self.index[end]] - heads[self.index[bone]]
            out[side] = d / np.linalg.norm(d)
        return out

    @property
    def faces(self) -> np.ndarray:
        """(F, 3) triangles of the mesh."""
        return self.model.get_triangular_faces().cpu().numpy().astype(np.int64)

    def dominant_bones(self) -> list[str]:
        """The bone with the largest skinning weight, per vertex."""
        w = self.model.vertex_bone_weights.cpu().numpy()
        i = self.model.vertex_bone_indices.cpu().numpy()
        best = i[np.arange(len(i)), np.argmax(w, axis=1)]
        return [self.labels[b] for b in best]
