"""Pose glue: parameter rows of the fit -> the body posed and standing on the floor.

World frame as design.md: z up, metres, the floor at z = 0. Each posture's root rotation is
``Rz(base_yaw + yaw) Ry(pitch) Rx(roll)``, ``base_yaw`` turning the template to face the
camera (postures 3 and 6 a further 90° to the right); its root height follows from floor
contact (the lower sole touches z = 0). Everything here accepts forward-mode dual tensors.
"""

from __future__ import annotations

import math

import torch

from torchfit._dual import is_dual, lift
from torchfit.body.model import BodyModel
from torchfit.body.postures import POSTURES, facing_yaw, nominal_joint_angles
from torchfit.errors import ModelError
from torchfit.fit.layout import JointBounds, ParamLayout

__all__ = ["DEFAULT_FREE_JOINTS", "euler_rotation", "Poser", "free_joints_for", "template_layout"]

_LIMB_DOFS = (
    "shoulder_flexion",
    "shoulder_abduct",
    "elbow_flexion",
    "hip_flexion",
    "hip_abduct",
    "knee_flexion",
)
_COMMON = tuple(f"{s}_{d}" for d in _LIMB_DOFS for s in "lr") + ("vc4_tilt", "vc4_roll")
# Some joints move a limb or the head along the line of sight, which the silhouette sees only
# through perspective and foreshortening; left free, the fit used them to match other things
# and they stay at their nominal 0:
# - in the side views (postures 3 and 6), hip abduction: a longer thigh and a lower knee match
#   as well (benchmarks/RESULTS.md, "The knee in posture 3");
# - the neck's side bend (``vc4_roll``) in the side views and its nod (``vc4_tilt``) in the
#   facing ones: a head turned 20-40 degrees along the line of sight drew a shorter body,
#   and the fit made the body taller to match (benchmarks/RESULTS.md, "The head's nod").
_SIDE = tuple(d for d in _COMMON if not d.endswith("hip_abduct") and d != "vc4_roll")
_FACING = tuple(d for d in _COMMON if d != "vc4_tilt")

#: Free joints per posture (design.md section 4); names absent from a template are skipped.
DEFAULT_FREE_JOINTS: dict[int, tuple[str, ...]] = {
    1: _FACING,
    2: _FACING,
    3: _SIDE + ("vl5_tilt", "l_ankle_flexion"),
    4: _FACING + ("l_shoulder_twisting", "r_shoulder_twisting"),
    5: _FACING + ("l_shoulder_twisting", "r_shoulder_twisting"),
    6: _SIDE + ("vl5_tilt",),
}


def free_joints_for(
    dof_names: list[str], poses: list[int], chosen: dict[str, list[str]] | None
) -> dict[int, list[str]]:
    """The free DOF names per posture: ``chosen["pose<j>"]`` where given, else the defaults
    (:data:`DEFAULT_FREE_JOINTS`, restricted to the template's DOFs)."""
    out = {}
    for j in poses:
        wanted = chosen.get(f"pose{j}") if chosen else None
        if wanted is None:
            wanted = [d for d in DEFAULT_FREE_JOINTS[j] if d in dof_names]
        out[j] = list(wanted)
    return out


def template_layout(
    model: BodyModel,
    poses: list[int],
    free_joints: dict[str, list[str]] | None = None,
    scale_bounds: tuple[float, float] = (0.4, 1.9),
    bounds: JointBounds | None = None,
) -> ParamLayout:
    """The fit's parameter layout for ``model``'s template in the postures ``poses``, with
    ``free_joints`` as :func:`free_joints_for` takes them.

    Raises:
        ConfigError: a free joint or DOF the template lacks.
    """
    return ParamLayout(
        model.template.scale_groups,
        model.dof_names,
        model.joint_lower,
        model.joint_upper,
        nominal_angles(model, poses),
        free_joints_for(list(model.dof_names), poses, free_joints),
        scale_bounds,
        bounds,
    )


def euler_rotation(yaw: torch.Tensor, roll: torch.Tensor, pitch: torch.Tensor) -> torch.Tensor:
    """R = Rz(yaw) Ry(pitch) Rx(roll), (B,) radians each -> (B, 3, 3)."""
    one, zero = torch.ones_like(yaw), torch.zeros_like(yaw)

    def mat(rows):
        return torch.stack([torch.stack(r, -1) for r in rows], -2)

    cz, sz, cy, sy, cx, sx = yaw.cos(), yaw.sin(), pitch.cos(), pitch.sin(), roll.cos(), roll.sin()
    rz = mat([[cz, -sz, zero], [sz, cz, zero], [zero, zero, one]])
    ry = mat([[cy, zero, sy], [zero, one, zero], [-sy, zero, cy]])
    rx = mat([[one, zero, zero], [zero, cx, -sx], [zero, sx, cx]])
    return rz @ ry @ rx


def nominal_angles(model: BodyModel, poses: list[int]) -> dict[int, torch.Tensor]:
    """Posture number -> (Q,) nominal joint angles of the template at that posture."""
    return {
        j: nominal_joint_angles(model.dof_names, POSTURES[j - 1], model.dtype).to(model.device)
        for j in poses
    }


class Poser:
    """Poses the body of parameter rows at a fitted posture, standing on the floor.

    Args:
        model: the body model.
        layout: the parameter layout.
        camera_centres: (B, 3) camera centres, world frame (for each subject's facing yaw).
    """

    def __init__(self, model: BodyModel, layout: ParamLayout, camera_centres: torch.Tensor):
        self.model = model
        self.layout = layout
        self.kw = {"dtype": model.dtype, "device": model.device}
        for name in ("l_sole", "r_sole"):
            if name not in model.template.landmarks:
                raise ModelError(f"template {model.template.name!r} lacks landmark {name!r}")
        self.soles = [model.template.landmarks["l_sole"], model.template.landmarks["r_sole"]]
        self.nominal = nominal_angles(model, list(layout.poses))
        facing = facing_yaw(camera_centres)
        self.base_yaw = {j: facing + math.radians(POSTURES[j - 1].turn_deg) for j in layout.poses}

    def state(self, full: torch.Tensor, j: int, rows: torch.Tensor):
        """Scales, angles and root of posture j for parameter rows ``full`` (N, P).

        Args:
            full: (N, P) parameters.
            j: the posture.
            rows: (N,) subject index of each row (for the yaw of its camera).

        Returns:
            scales (N, S, 3), joint angles (N, Q), root rotation (N, 3, 3), translation (N, 3).
        """
        m = self.model
        scales = m.expand_scales(self.layout.group_scales(full))
        block = self.layout.blocks[j]
        n_joint = block.num_joints
        dual = is_dual(full)
        # scatter the free joints without in-place writes (dual tensors flow through)
        onehot = torch.zeros(n_joint, m.num_dofs, **self.kw)
        onehot[torch.arange(n_joint), torch.tensor(block.dofs, dtype=torch.long)] = 1.0
        fixed = lift((self.nominal[j] * (1 - onehot.sum(0))).expand(full.shape[0], -1), dual)
        free = full[:, block.joints]
        angles = fixed + free @ lift(onehot, dual)
        tx, ty, yaw, roll, pitch = full[:, block.root].unbind(-1)
        rot = euler_rotation(lift(self.base_yaw[j][rows], dual) + yaw, roll, pitch)
        trans = torch.stack([tx, ty, torch.zeros_like(tx)], -1)
        return scales, angles, rot, trans

    def world(
        self,
        full: torch.Tensor,
        j: int,
        rows: torch.Tensor,
        vertex_index: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed vertices and segment origins of posture j, standing on the floor.

        Args:
            full: (N, P) parameters.
            j: the posture.
            rows: (N,) subject index of each row.
            vertex_index: optional (K,) template vertices to pose (default: all).

        Returns:
            (N, K, 3) vertices and (N, S, 3) segment origins, metres, world frame.
        """
        return self._on_floor(self.state(full, j, rows), vertex_index)

    def world_postures(
        self,
        full: torch.Tensor,
        poses: list[int],
        rows: torch.Tensor,
        vertex_index: torch.Tensor | None = None,
    ) -> list[torch.Tensor]:
        """The vertices of several postures, standing on the floor, from one model call over
        all their rows (the kinematics' cost is mostly per call): per posture in ``poses``,
        the (N, K, 3) vertices :meth:`world` gives (``vertex_index`` (K,), default: all)."""
        states = [self.state(full, j, rows) for j in poses]
        state = tuple(torch.cat(part) for part in zip(*states, strict=True))
        return list(self._on_floor(state, vertex_index)[0].split(full.shape[0]))

    def _on_floor(
        self, state: tuple, vertex_index: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Vertices ``vertex_index`` (default: all) and segment origins of the posed
        :meth:`state`, lifted so that the lower sole touches z = 0."""
        scales, angles, rot, trans = state
        device = scales.device
        if vertex_index is None:
            vertex_index = torch.arange(self.model.template.vertices.shape[0], device=device)
        idx = torch.cat([vertex_index, torch.tensor(self.soles, device=device)])
        out = self.model(scales, angles, trans, rot, vertex_index=idx)
        verts = out.vertices
        floor = torch.minimum(verts[:, -2, 2], verts[:, -1, 2])
        zero = torch.zeros_like(floor)
        lift_z = torch.stack([zero, zero, floor], -1)[:, None]
        return verts[:, :-2] - lift_z, out.origins - lift_z

    def columns(self, j: int) -> torch.Tensor:
        """(C_j,) the parameter columns posture j depends on, in the order of
        :meth:`world_jacobian`'s derivatives: every scale, then the posture's block."""
        block = self.layout.blocks[j]
        scales = torch.arange(self.layout.num_scale_params)
        return torch.cat([scales, torch.arange(block.start, block.columns.stop)])

    def world_jacobian(
        self,
        full: torch.Tensor,
        j: int,
        rows: torch.Tensor,
        vertex_index: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed, floor-standing vertices of posture j and their derivatives, in closed form.

        The model gives the derivatives w.r.t. each segment's scales and each joint angle
        (:meth:`BodyModel.jacobian`); a scale group's column is the sum over its segments.
        The root ``Rz(ψ) Ry(θ) Rx(φ)`` turns every point about the root origin ``t``: yaw
        about ``e_z``, pitch about ``Rz e_y`` and roll about ``R e_x``, so each column is
        ``axis × (p − t)``; ``tx`` and ``ty`` move every point along ``e_x`` and ``e_y``.
        Floor contact subtracts the lower sole's height, and with it its derivative (the
        mean of both soles' at a tie, as forward-mode AD of ``torch.minimum`` gives it).

        Args:
            full: (N, P) parameters (plain tensors).
            j: the posture.
            rows: (N,) subject index of each row.
            vertex_index: (K,) template vertices to pose.

        Returns:
            (N, K, 3) vertices, as :meth:`world` gives them, and (N, K, 3, C_j) their
            derivatives w.r.t. the columns :meth:`columns` names.
        """
        m = self.model
        scales, angles, rot, trans = self.state(full, j, rows)
        soles = torch.tensor(self.soles, device=full.device)
        idx = torch.cat([vertex_index, soles])
        block = self.layout.blocks[j]
        dofs = torch.tensor(block.dofs, dtype=torch.long, device=full.device)
        group = m.template.segment_group.to(full.device)
        out, d_group, d_joints = m.jacobian(scales, angles, trans, rot, idx, dofs, group)
        p = out.vertices
        n, k = p.shape[:2]
        # the root: tx, ty, yaw, roll, pitch
        rel = p - trans[:, None]
        psi = self.base_yaw[j][rows] + full[:, block.root_column("yaw")]
        zero = torch.zeros_like(psi)
        pitch_axis = torch.stack([-psi.sin(), psi.cos(), zero], -1)
        axes = torch.stack([torch.stack([zero, zero, zero + 1], -1), rot[..., 0], pitch_axis], 1)
        turn = torch.linalg.cross(axes[:, None].expand(-1, k, -1, -1), rel[:, :, None])
        move = torch.zeros(n, k, 3, 2, dtype=p.dtype, device=p.device)
        move[:, :, 0, 0] = 1.0
        move[:, :, 1, 1] = 1.0
        d_root = torch.cat([move, turn.transpose(2, 3)], -1)  # tx, ty, yaw, roll, pitch
        d = torch.cat([d_group.reshape(n, k, 3, -1), d_joints, d_root], -1)
        # floor contact
        zl, zr = p[:, -2, 2], p[:, -1, 2]
        wl = (zl < zr).to(p) + 0.5 * (zl == zr).to(p)
        d_floor = wl[:, None] * d[:, -2, 2] + (1 - wl[:, None]) * d[:, -1, 2]  # (N, C_j)
        floor = torch.minimum(zl, zr)
        world = p[:, :-2].clone()
        world[..., 2] -= floor[:, None]
        d_world = d[:, :-2].clone()
        d_world[:, :, 2] -= d_floor[:, None]
        return world, d_world
