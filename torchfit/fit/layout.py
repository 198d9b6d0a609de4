"""The one owner of the fit's parameter and residual layout.

Parameters per subject (one row of ``x``, ``(B, P)``):

- the free scales: one (σx, σy, σz) triple per scale group, group-major (``scale:<group>:<axis>``);
- per fitted posture j, in ``poses`` order: the posture's free joint angles (absolute,
  radians; ``pose<j>:<dof>``), then the root offsets ``tx, ty`` (floor translation, metres)
  and ``yaw, roll, pitch`` (radians from the nominal "facing the camera" orientation).

Residuals per subject (one row of ``r``, ``(B, M)``): for every fitted posture, e_P (one entry
per person contour pixel, padded to the batch maximum ``C_j``) followed by e_M (one entry);
then e_B, one entry per parameter; then, where the problem has them (:mod:`torchfit.fit.prior`),
e_S, one entry per prior scale entry, and e_H, the known-height entry.

Every other module asks :class:`ParamLayout` and :class:`ResidualLayout` where a parameter or a
residual lives instead of computing offsets itself.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch

from torchfit.body.postures import POSTURES
from torchfit.errors import ConfigError

__all__ = [
    "ROOT_NAMES",
    "SCALE_ALIASES",
    "PoseBlock",
    "ParamLayout",
    "ResidualLayout",
    "JointBounds",
]

#: The root offsets of every posture, in their order within the posture's block.
ROOT_NAMES: tuple[str, ...] = ("tx", "ty", "yaw", "roll", "pitch")

#: Stage aliases for scale groups: "group" (all three axes) or "group:axes".
SCALE_ALIASES: dict[str, tuple[str, ...]] = {
    "legs": ("thigh:z", "calf:z"),
    "upper_body": ("pelvis", "abdomen", "chest", "torso", "upperarm:z", "forearm:z"),
}


@dataclass(frozen=True)
class JointBounds:
    """Interval limits of the root offsets (the joint angles use the template's limits).

    Attributes:
        translation_max_m: the floor translation interval, each axis, metres.
        yaw_max_deg: the yaw interval around the nominal view, degrees.
        tilt_max_deg: the roll / pitch interval, degrees.
        side_roll_max_deg: the roll interval in the side views (postures 3 and 6), degrees
            (``None``: ``tilt_max_deg``).
    """

    translation_max_m: float = 0.15
    yaw_max_deg: float = 15.0
    tilt_max_deg: float = 5.0
    side_roll_max_deg: float | None = None


@dataclass(frozen=True)
class PoseBlock:
    """Where one posture's parameters live in a row of ``x``.

    Attributes:
        pose: the posture number, 1..6.
        dofs: the template DOF indices of its free joints, in parameter order.
        start: the column of its first parameter.
    """

    pose: int
    dofs: tuple[int, ...]
    start: int

    @property
    def num_joints(self) -> int:
        """Number of free joint angles."""
        return len(self.dofs)

    @property
    def joints(self) -> slice:
        """Columns of the free joint angles."""
        return slice(self.start, self.start + self.num_joints)

    @property
    def root(self) -> slice:
        """Columns of the root offsets (``ROOT_NAMES`` order)."""
        return slice(self.joints.stop, self.joints.stop + len(ROOT_NAMES))

    @property
    def columns(self) -> slice:
        """All the posture's columns."""
        return slice(self.start, self.root.stop)

    def root_column(self, name: str) -> int:
        """The column of one root offset (``"tx"``, ``"ty"``, ``"yaw"``, ``"roll"``,
        ``"pitch"``)."""
        return self.root.start + ROOT_NAMES.index(name)


class ParamLayout:
    """Names, bounds, start values and column ranges of the fit parameters.

    Args:
        scale_groups: the template's scale groups.
        dof_names: the template's joint DOF names.
        joint_lower, joint_upper: (Q,) joint limits, radians.
        nominal: posture number -> (Q,) nominal joint angles of that posture.
        free_joints: posture number -> the free DOF names of that posture, in order.
        scale_bounds: (min, max) of every scale.
        bounds: the root offsets' intervals.
    """

    def __init__(
        self,
        scale_groups: Sequence[str],
        dof_names: Sequence[str],
        joint_lower: torch.Tensor,
        joint_upper: torch.Tensor,
        nominal: Mapping[int, torch.Tensor],
        free_joints: Mapping[int, Sequence[str]],
        scale_bounds: tuple[float, float] = (0.4, 1.9),
        bounds: JointBounds | None = None,
    ) -> None:
        bounds = bounds or JointBounds()
        self.scale_groups = tuple(scale_groups)
        self.dof_names = tuple(dof_names)
        self.poses = tuple(free_joints)
        g = len(self.scale_groups)
        names = [f"scale:{grp}:{a}" for grp in self.scale_groups for a in "xyz"]
        lower = [float(scale_bounds[0])] * (3 * g)
        upper = [float(scale_bounds[1])] * (3 * g)
        init = [1.0] * (3 * g)
        t_max = bounds.translation_max_m
        yaw_max = math.radians(bounds.yaw_max_deg)
        tilt_max = math.radians(bounds.tilt_max_deg)
        self.blocks: dict[int, PoseBlock] = {}
        for j, wanted in free_joints.items():
            unknown = [d for d in wanted if d not in self.dof_names]
            if unknown:
                raise ConfigError(f"free_joints.pose{j}: unknown joint DOFs {unknown}")
            dofs = tuple(self.dof_names.index(d) for d in wanted)
            self.blocks[j] = PoseBlock(j, dofs, len(names))
            names += [f"pose{j}:{self.dof_names[d]}" for d in dofs]
            lower += [float(joint_lower[d]) for d in dofs]
            upper += [float(joint_upper[d]) for d in dofs]
            init += [float(nominal[j][d]) for d in dofs]
            names += [f"pose{j}:{r}" for r in ROOT_NAMES]
            roll_max = tilt_max
            if bounds.side_roll_max_deg is not None and POSTURES[j - 1].turn_deg != 0:
                roll_max = math.radians(bounds.side_roll_max_deg)
            lower += [-t_max, -t_max, -yaw_max, -roll_max, -tilt_max]
            upper += [t_max, t_max, yaw_max, roll_max, tilt_max]
            init += [0.0] * len(ROOT_NAMES)
        self.names: tuple[str, ...] = tuple(names)
        self.num_scale_params = 3 * g
        self._lower, self._upper, self._init = lower, upper, init

    # ---- sizes and values -------------------------------------------------------------
    @property
    def num_params(self) -> int:
        """P, the width of a parameter row."""
        return len(self.names)

    def lower(self, **kw) -> torch.Tensor:
        """(P,) lower bounds (``kw``: dtype, device)."""
        return torch.tensor(self._lower, **kw)

    def upper(self, **kw) -> torch.Tensor:
        """(P,) upper bounds (``kw``: dtype, device)."""
        return torch.tensor(self._upper, **kw)

    def initial(self, **kw) -> torch.Tensor:
        """(P,) the template start: unit scales, nominal angles, root on the mark."""
        return torch.tensor(self._init, **kw)

    def index(self, name: str) -> int | None:
        """The column of a named parameter, or None."""
        return self.names.index(name) if name in self.names else None

    # ---- scales -------------------------------------------------------------------------
    @property
    def scales(self) -> slice:
        """Columns of the group scales."""
        return slice(0, self.num_scale_params)

    def group_scales(self, x: torch.Tensor) -> torch.Tensor:
        """(N, G, 3) group scales of parameter rows ``x`` (N, P)."""
        return x[:, self.scales].reshape(x.shape[0], len(self.scale_groups), 3)

    def scale_column(self, group: str, axis: str) -> int | None:
        """The column of one group scale axis (None when the template lacks the group)."""
        return self.index(f"scale:{group}:{axis}")

    def scale_indices(self, names: Sequence[str]) -> list[int]:
        """Columns of the group scales named by a stage's ``scales`` list: groups, aliases
        (:data:`SCALE_ALIASES`), ``"group:axes"`` or ``"all"``."""
        groups = self.scale_groups
        chosen: list[int] = []
        for name in names:
            entries = groups if name == "all" else SCALE_ALIASES.get(name, (name,))
            for entry in entries:
                group, _, axes = entry.partition(":")
                if group not in groups:
                    if name in SCALE_ALIASES:  # aliases may name groups a template lacks
                        continue
                    raise ConfigError(
                        f"stage scales: unknown scale group {group!r} (groups: {list(groups)}, "
                        f"aliases: {sorted(SCALE_ALIASES)} and 'all')"
                    )
                for axis in axes or "xyz":
                    if axis not in "xyz":
                        raise ConfigError(f"stage scales: bad axis {axis!r} in {entry!r}")
                    chosen.append(groups.index(group) * 3 + "xyz".index(axis))
        return sorted(set(chosen))

    # ---- postures -----------------------------------------------------------------------
    def free_indices(self, scales: Sequence[str], joints: bool, root: bool) -> list[int]:
        """Columns a stage frees: the named scales, and every posture's joints and/or root."""
        idx = self.scale_indices(scales)
        for block in self.blocks.values():
            if joints:
                idx += list(range(block.joints.start, block.joints.stop))
            if root:
                idx += list(range(block.root.start, block.root.stop))
        return sorted(set(idx))

    def root_offsets(self, x: torch.Tensor, j: int) -> dict[str, float]:
        """The root offsets of posture j in one parameter row ``x`` (P,), by name."""
        values = x[self.blocks[j].root].tolist()
        return dict(zip(ROOT_NAMES, values, strict=True))

    def free_joint_names(self, j: int) -> list[str]:
        """The free DOF names of posture j."""
        return [self.dof_names[d] for d in self.blocks[j].dofs]

    def residual_layout(
        self,
        contour_lengths: Sequence[int],
        num_prior: int = 0,
        num_facts: int = 0,
        num_pose_prior: int = 0,
        num_marks: int = 0,
    ) -> ResidualLayout:
        """The residual layout for padded person contour lengths ``C_j`` (``poses`` order),
        with ``num_prior`` prior entries, ``num_facts`` known-fact entries,
        ``num_pose_prior`` posture-prior entries and ``num_marks`` joint-mark entries after
        e_B."""
        return ResidualLayout(
            self.poses,
            tuple(contour_lengths),
            self.num_params,
            num_prior,
            num_facts,
            num_pose_prior,
            num_marks,
        )


@dataclass(frozen=True)
class ResidualLayout:
    """Where each term lives in a residual row.

    Attributes:
        poses: the fitted postures, in order.
        contour_lengths: padded person contour length ``C_j`` of each posture.
        num_params: number of barrier entries (one per parameter).
        num_prior: number of prior entries e_S (after e_B).
        num_facts: number of known-fact entries e_H (after e_S).
        num_pose_prior: number of posture-prior entries e_A (after e_H).
        num_marks: number of joint-mark entries e_J (after e_A; two per marked joint).
    """

    poses: tuple[int, ...]
    contour_lengths: tuple[int, ...]
    num_params: int
    num_prior: int = 0
    num_facts: int = 0
    num_pose_prior: int = 0
    num_marks: int = 0

    def block(self, j: int) -> slice:
        """Columns of posture j's ``[e_P..., e_M]``."""
        k = self.poses.index(j)
        start = sum(n + 1 for n in self.contour_lengths[:k])
        return slice(start, start + self.contour_lengths[k] + 1)

    def e_p(self, j: int) -> slice:
        """Columns of posture j's e_P entries."""
        block = self.block(j)
        return slice(block.start, block.stop - 1)

    def e_m(self, j: int) -> int:
        """The column of posture j's e_M."""
        return self.block(j).stop - 1

    @property
    def barrier(self) -> slice:
        """Columns of e_B."""
        start = sum(n + 1 for n in self.contour_lengths)
        return slice(start, start + self.num_params)

    @property
    def prior(self) -> slice:
        """Columns of e_S (empty without a prior)."""
        return slice(self.barrier.stop, self.barrier.stop + self.num_prior)

    @property
    def facts(self) -> slice:
        """Columns of e_H (empty without known facts)."""
        return slice(self.prior.stop, self.prior.stop + self.num_facts)

    @property
    def pose_prior(self) -> slice:
        """Columns of e_A (empty without a posture prior)."""
        return slice(self.facts.stop, self.facts.stop + self.num_pose_prior)

    @property
    def marks(self) -> slice:
        """Columns of e_J (empty without joint marks)."""
        return slice(self.pose_prior.stop, self.pose_prior.stop + self.num_marks)

    @property
    def size(self) -> int:
        """M, the width of a residual row."""
        return self.marks.stop

    def per_pose_quality(self, r: torch.Tensor) -> dict[int, tuple[float, float]]:
        """Posture -> (RMS of e_P, e_M) in pixels for one residual row ``r`` (M,)."""
        return {j: (float(r[self.e_p(j)].norm()), float(r[self.e_m(j)])) for j in self.poses}
