"""The six-posture silhouette fit (first paper, sections 6–8; design.md section 6), batched.

Parameters per subject (one row of ``x``):

- free scales: one (σx, σy, σz) triple per scale group (left/right and spine segments share);
- per pose j: the pose's free joint angles (absolute, radians), the floor translation (tx, ty)
  in metres, and the root rotation offsets (yaw, roll, pitch) in radians from the nominal
  "facing the camera" orientation (postures 3 and 6 turned 90° to the right). The height of the
  root follows from floor contact: the lower sole touches z = 0.

The residual per subject stacks, for every pose, e_P (one entry per person contour pixel,
padded to the batch maximum and masked) and e_M (one entry), then e_B for every parameter.
A fit runs as a list of stages; each stage frees a subset of the parameters.

The Jacobian is computed in forward mode with the discrete contour choice made once per
evaluation point; each pose's block only carries the tangents of the parameters it depends
on (the scales and that pose's own parameters), folded into the batch dimension.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.autograd.forward_ad as fwad

from torchfit._dual import is_dual, lift
from torchfit.body.model import BodyModel
from torchfit.body.postures import POSTURES, facing_yaw, nominal_joint_angles
from torchfit.camera import Camera, camera_centre, project_points
from torchfit.config import FitConfig, ModelConfig, StageConfig
from torchfit.errors import ConfigError, ModelError, ShapeError
from torchfit.image.contours import trace_outer_contour
from torchfit.image.distance import mask_to_distance_map, sample_distance_map
from torchfit.model_contour import (
    ContourEndpoints,
    ContourSelection,
    EdgeSampler,
    contour_endpoints,
    point_to_edge_distance,
    select_contour,
)
from torchfit.residuals import barrier, model_to_person, person_to_model

__all__ = [
    "PersonData",
    "SilhouetteFit",
    "DEFAULT_FREE_JOINTS",
    "scale_selection",
    "person_data_from_masks",
]

_LIMB_DOFS = (
    "shoulder_flexion",
    "shoulder_abduct",
    "elbow_flexion",
    "hip_flexion",
    "hip_abduct",
    "knee_flexion",
)
_COMMON = tuple(f"{s}_{d}" for d in _LIMB_DOFS for s in "lr") + ("vc4_tilt", "vc4_roll")

#: Free joints per posture (design.md section 4); names absent from a template are skipped.
DEFAULT_FREE_JOINTS: dict[int, tuple[str, ...]] = {
    1: _COMMON,
    2: _COMMON,
    3: _COMMON + ("vl5_tilt", "l_ankle_flexion"),
    4: _COMMON + ("l_shoulder_twisting", "r_shoulder_twisting"),
    5: _COMMON + ("l_shoulder_twisting", "r_shoulder_twisting"),
    6: _COMMON + ("vl5_tilt",),
}

#: Stage aliases for scale groups: "group" (all three axes) or "group:axes".
SCALE_ALIASES: dict[str, tuple[str, ...]] = {
    "legs": ("thigh:z", "calf:z"),
    "upper_body": ("pelvis", "abdomen", "chest", "torso", "upperarm:z", "forearm:z"),
}

_ROOT = ("tx", "ty", "yaw", "roll", "pitch")


@dataclass
class PersonData:
    """The fixed person side of B subjects, six poses each.

    Attributes:
        contours: 6 tensors (B, C_j, 2) of person contour pixels (u, v), padded.
        valid: 6 bool tensors (B, C_j).
        distance_maps: 6 tensors (B, H, W): D_P, pixels to the person's contour (finite).
        camera: B cameras.
        uncertain: optional 6 bool tensors (B, H, W): pixels where the silhouette is not to be
            trusted (those the segmentation's shadow test removed). A model contour point on
            such a pixel does not count in e_M, and ``valid`` already excludes the person
            contour pixels next to them (see :func:`person_data_from_masks`).
    """

    contours: list[torch.Tensor]
    valid: list[torch.Tensor]
    distance_maps: list[torch.Tensor]
    camera: Camera
    uncertain: list[torch.Tensor] | None = None

    @property
    def batch_size(self) -> int:
        return self.camera.batch_size


def scale_selection(model: BodyModel, names: list[str]) -> list[int]:
    """Indices into the flattened (G*3) group scales named by a stage's ``scales`` list."""
    groups = model.template.scale_groups
    chosen: list[int] = []
    for name in names:
        entries = (f"{g}" for g in groups) if name == "all" else SCALE_ALIASES.get(name, (name,))
        for entry in entries:
            group, _, axes = entry.partition(":")
            if group not in groups:
                if name in SCALE_ALIASES:  # aliases may name groups a template lacks
                    continue
                raise ConfigError(
                    f"stage scales: unknown scale group {group!r} (groups: {groups}, "
                    f"aliases: {sorted(SCALE_ALIASES)} and 'all')"
                )
            for axis in axes or "xyz":
                if axis not in "xyz":
                    raise ConfigError(f"stage scales: bad axis {axis!r} in {entry!r}")
                chosen.append(groups.index(group) * 3 + "xyz".index(axis))
    return sorted(set(chosen))


def _rotation(yaw: torch.Tensor, roll: torch.Tensor, pitch: torch.Tensor) -> torch.Tensor:
    """R = Rz(yaw) Ry(pitch) Rx(roll), (B,) each -> (B, 3, 3)."""
    one, zero = torch.ones_like(yaw), torch.zeros_like(yaw)

    def mat(rows):
        return torch.stack([torch.stack(r, -1) for r in rows], -2)

    cz, sz, cy, sy, cx, sx = yaw.cos(), yaw.sin(), pitch.cos(), pitch.sin(), roll.cos(), roll.sin()
    rz = mat([[cz, -sz, zero], [sz, cz, zero], [zero, zero, one]])
    ry = mat([[cy, zero, sy], [zero, one, zero], [-sy, zero, cy]])
    rx = mat([[one, zero, zero], [zero, cx, -sx], [zero, sx, cx]])
    return rz @ ry @ rx


class SilhouetteFit:
    """The fitting problem for a batch of subjects.

    Args:
        model: the body model (its dtype and device are used).
        person: the person data of B subjects.
        fit_config: poses, free joints, bounds, contour sampling.
        model_config: scale bounds.
    """

    def __init__(
        self,
        model: BodyModel,
        person: PersonData,
        fit_config: FitConfig | None = None,
        model_config: ModelConfig | None = None,
    ) -> None:
        self.model = model
        self.person = person
        self.cfg = fit_config or FitConfig()
        mcfg = model_config or ModelConfig()
        self.model_cfg = mcfg
        kw = {"dtype": model.dtype, "device": model.device}
        self.kw = kw
        self.batch = person.batch_size
        self.camera = person.camera.to(device=model.device, dtype=model.dtype)
        self.poses = list(self.cfg.poses)
        self.sampler = EdgeSampler(model.faces, self.cfg.samples_per_edge)
        for name in ("l_sole", "r_sole"):
            if name not in model.template.landmarks:
                raise ModelError(f"template {model.template.name!r} lacks landmark {name!r}")
        self._soles = [model.template.landmarks["l_sole"], model.template.landmarks["r_sole"]]

        # ---- layout of the full parameter vector
        g = model.num_groups
        names = [f"scale:{grp}:{a}" for grp in model.template.scale_groups for a in "xyz"]
        lower = [mcfg.scale_min] * (3 * g)
        upper = [mcfg.scale_max] * (3 * g)
        init = [1.0] * (3 * g)
        self.pose_slices: dict[int, slice] = {}
        self.pose_joints: dict[int, list[int]] = {}
        self.nominal: dict[int, torch.Tensor] = {}
        centre = camera_centre(self.camera.R, self.camera.t)
        self.base_yaw = {}
        t_max = self.cfg.translation_max_m
        yaw_max, tilt_max = math.radians(self.cfg.yaw_max_deg), math.radians(self.cfg.tilt_max_deg)
        for j in self.poses:
            posture = POSTURES[j - 1]
            nominal = nominal_joint_angles(model.dof_names, posture, model.dtype).to(model.device)
            self.nominal[j] = nominal
            wanted = self.cfg.free_joints.get(f"pose{j}") if self.cfg.free_joints else None
            if wanted is not None:
                unknown = [d for d in wanted if d not in model.dof_names]
                if unknown:
                    raise ConfigError(f"fit.free_joints.pose{j}: unknown joint DOFs {unknown}")
            else:
                wanted = [d for d in DEFAULT_FREE_JOINTS[j] if d in model.dof_names]
            dofs = [model.dof_index(d) for d in wanted]
            self.pose_joints[j] = dofs
            start = len(names)
            names += [f"pose{j}:{model.dof_names[d]}" for d in dofs]
            lower += [float(model.joint_lower[d]) for d in dofs]
            upper += [float(model.joint_upper[d]) for d in dofs]
            init += [float(nominal[d]) for d in dofs]
            names += [f"pose{j}:{r}" for r in _ROOT]
            lower += [-t_max, -t_max, -yaw_max, -tilt_max, -tilt_max]
            upper += [t_max, t_max, yaw_max, tilt_max, tilt_max]
            init += [0.0] * 5
            self.pose_slices[j] = slice(start, len(names))
            self.base_yaw[j] = facing_yaw(centre) + math.radians(posture.turn_deg)
        self.names = names
        self.lower = torch.tensor(lower, **kw)
        self.upper = torch.tensor(upper, **kw)
        self._init = torch.tensor(init, **kw)
        self.num_scale_params = 3 * g

    def subset(self, index: list[int]) -> SilhouetteFit:
        """The same problem for a subset of the subjects (same layout and residual width)."""
        idx = torch.as_tensor(index, dtype=torch.long)
        p, cam = self.person, self.person.camera
        person = PersonData(
            [c[idx] for c in p.contours],
            [v[idx] for v in p.valid],
            [d[idx] for d in p.distance_maps],
            Camera(
                K=cam.K[idx],
                dist=cam.dist[idx],
                R=cam.R[idx],
                t=cam.t[idx],
                image_size=cam.image_size,
            ),
            None if p.uncertain is None else [u[idx] for u in p.uncertain],
        )
        return SilhouetteFit(self.model, person, self.cfg, self.model_cfg)

    # ------------------------------------------------------------------------------------
    @property
    def num_params(self) -> int:
        return len(self.names)

    def initial_params(self) -> torch.Tensor:
        """(B, P) the template start: unit scales, nominal angles, root on the mark."""
        return self._init.expand(self.batch, -1).clone()

    def stage_indices(self, stage: StageConfig) -> torch.Tensor:
        """Indices of the parameters a stage frees."""
        idx = scale_selection(self.model, list(stage.scales))
        for j in self.poses:
            sl = self.pose_slices[j]
            n_joint = len(self.pose_joints[j])
            if stage.joints:
                idx += list(range(sl.start, sl.start + n_joint))
            if stage.root:
                idx += list(range(sl.start + n_joint, sl.stop))
        if not idx:
            raise ConfigError(f"fit stage {stage.name!r} frees no parameter")
        return torch.tensor(sorted(set(idx)), device=self.model.device)

    # ------------------------------------------------------------------------------------
    def pose_state(self, full: torch.Tensor, j: int, rows: torch.Tensor):
        """Scales, angles and root of pose j for parameter rows ``full`` (N, P).

        Args:
            rows: (N,) subject index of each row (for the yaw of its camera).

        Returns:
            scales (N, S, 3), joint angles (N, Q), root rotation (N, 3, 3), translation (N, 3).
        """
        m = self.model
        scales = m.expand_scales(full[:, : self.num_scale_params].reshape(-1, m.num_groups, 3))
        sl = self.pose_slices[j]
        n_joint = len(self.pose_joints[j])
        dual = is_dual(full)
        # scatter the free joints without in-place writes (dual tensors flow through)
        onehot = torch.zeros(n_joint, m.num_dofs, **self.kw)
        onehot[torch.arange(n_joint), torch.tensor(self.pose_joints[j])] = 1.0
        fixed = lift((self.nominal[j] * (1 - onehot.sum(0))).expand(full.shape[0], -1), dual)
        free = full[:, sl.start : sl.start + n_joint]
        angles = fixed + free @ lift(onehot, dual)
        tx, ty, yaw, roll, pitch = full[:, sl.start + n_joint : sl.stop].unbind(-1)
        rot = _rotation(lift(self.base_yaw[j][rows], dual) + yaw, roll, pitch)
        trans = torch.stack([tx, ty, torch.zeros_like(tx)], -1)
        return scales, angles, rot, trans

    def pose_world(
        self,
        full: torch.Tensor,
        j: int,
        rows: torch.Tensor,
        vertex_index: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed vertices and segment origins of pose j, standing on the floor (world frame).

        Args:
            full: (N, P) parameters.
            rows: (N,) subject index of each row.
            vertex_index: optional (K,) template vertices to pose (default: all).

        Returns:
            (N, K, 3) vertices and (N, S, 3) segment origins, metres.
        """
        scales, angles, rot, trans = self.pose_state(full, j, rows)
        soles = torch.tensor(self._soles, device=full.device)
        if vertex_index is None:
            vertex_index = torch.arange(self.model.template.vertices.shape[0], device=full.device)
        idx = torch.cat([vertex_index, soles])
        out = self.model(scales, angles, trans, rot, vertex_index=idx)
        verts = out.vertices
        floor = torch.minimum(verts[:, -2, 2], verts[:, -1, 2])
        zero = torch.zeros_like(floor)
        lift_z = torch.stack([zero, zero, floor], -1)[:, None]
        return verts[:, :-2] - lift_z, out.origins - lift_z

    def project(self, points: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """(N, K, 2) pixels of world points (N, K, 3) in each row's camera."""
        cam = self.camera
        cam_rows = Camera(
            K=cam.K[rows],
            dist=cam.dist[rows],
            R=cam.R[rows],
            t=cam.t[rows],
            image_size=cam.image_size,
        )
        return project_points(points, cam_rows)

    def pose_pixels(
        self,
        full: torch.Tensor,
        j: int,
        rows: torch.Tensor,
        vertex_index: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Posed, floor-standing vertices of pose j projected into each row's camera.

        Args:
            full: (N, P) parameters.
            rows: (N,) subject index of each row.
            vertex_index: optional (K,) template vertices to project (default: all).

        Returns:
            (N, K, 2) pixels.
        """
        return self.project(self.pose_world(full, j, rows, vertex_index)[0], rows)

    @torch.no_grad()
    def select(self, full: torch.Tensor) -> dict[int, ContourSelection]:
        """The discrete model-contour choice at ``full`` (B, P), one per pose."""
        rows = torch.arange(self.batch, device=full.device)
        out = {}
        for k, j in enumerate(self.poses):
            pixels = self.pose_pixels(full, j, rows)
            out[j] = select_contour(
                self.sampler,
                pixels,
                self.person.contours[k],
                self.person.valid[k],
                self.camera.image_size,
                self.cfg.contour_tolerance_px,
            )
        return out

    def _sample_rows(self, k: int, rows: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Bilinear D_P of pose index k for each row's subject at (N, n, 2) points."""
        dmap = self.person.distance_maps[k].to(points.dtype)  # (B, H, W)
        return sample_distance_map(dmap.unsqueeze(1), points, rows)

    def _terms(
        self, k: int, rows: torch.Tensor, ends: ContourEndpoints, pix: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """e_P (N, C) and the model contour points (N, N_m, 2) from endpoint pixels ``pix``."""
        contour = self.person.contours[k][rows].to(pix["pa"])
        valid = self.person.valid[k][rows]
        dist = point_to_edge_distance(
            contour, pix["pa"], pix["pb"], ends.person_t.to(contour), 0.5 / self.sampler.k
        )
        t = ends.model_t.to(contour)[..., None]
        points = pix["ma"] * (1 - t) + pix["mb"] * t
        return person_to_model(dist, valid), points

    def _endpoint_pixels(
        self, pixels: torch.Tensor, lookup: torch.Tensor, ends: ContourEndpoints
    ) -> dict[str, torch.Tensor]:
        r = torch.arange(pixels.shape[0], device=pixels.device)[:, None]
        return {
            "pa": pixels[r, lookup[ends.person_a]],
            "pb": pixels[r, lookup[ends.person_b]],
            "ma": pixels[r, lookup[ends.model_a]],
            "mb": pixels[r, lookup[ends.model_b]],
        }

    def _prepare(
        self, sel: ContourSelection
    ) -> tuple[ContourEndpoints, torch.Tensor, torch.Tensor]:
        ends = contour_endpoints(self.sampler, sel)
        vidx = ends.vertices()
        lookup = torch.zeros(
            self.model.template.vertices.shape[0], dtype=torch.long, device=vidx.device
        )
        lookup[vidx] = torch.arange(vidx.numel(), device=vidx.device)
        return ends, vidx, lookup

    def _pose_terms(
        self,
        k: int,
        rows: torch.Tensor,
        ends: ContourEndpoints,
        sel: ContourSelection,
        pix: dict[str, torch.Tensor],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        e_p, points = self._terms(k, rows, ends, pix)
        valid = sel.sample_valid
        if self.person.uncertain is not None:
            valid = valid & ~self._uncertain_at(k, rows, points)
        e_m = model_to_person(self._sample_rows(k, rows, points), valid)
        return e_p, e_m

    def _uncertain_at(self, k: int, rows: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """(N, n) bool: the uncertain flag of pose index k at the pixel nearest each point (a
        choice, like the contour's, made at each evaluation point)."""
        flags = self.person.uncertain[k].to(points.device)  # (B, H, W)
        h, w = flags.shape[-2:]
        p = points.detach()
        u = p[..., 0].round().clamp(0, w - 1).long()
        v = p[..., 1].round().clamp(0, h - 1).long()
        return flags[rows[:, None].expand_as(u), v, u]

    def pose_residual(
        self, full: torch.Tensor, j: int, rows: torch.Tensor, selection: ContourSelection
    ) -> torch.Tensor:
        """[e_P (C_j entries), e_M] of pose j for rows ``full`` (N, P) -> (N, C_j + 1)."""
        k = self.poses.index(j)
        ends, vidx, lookup = self._prepare(selection)
        pixels = self.pose_pixels(full, j, rows, vidx)
        e_p, e_m = self._pose_terms(
            k, rows, ends, selection, self._endpoint_pixels(pixels, lookup, ends)
        )
        return torch.cat([e_p, e_m[:, None]], dim=1)

    def residual_mask(self) -> torch.Tensor:
        """(B, M) validity of the residual entries (padding of e_P is False)."""
        parts = [
            torch.cat([v, torch.ones(self.batch, 1, dtype=torch.bool, device=v.device)], 1)
            for v in self.person.valid
        ]
        parts.append(
            torch.ones(
                self.batch, self.num_params, dtype=torch.bool, device=self.person.valid[0].device
            )
        )
        return torch.cat(parts, 1)

    def barrier_residual(self, full: torch.Tensor) -> torch.Tensor:
        return barrier(full, self.lower, self.upper, self.cfg.barrier_weight)

    def residual(
        self, full: torch.Tensor, selections: dict[int, ContourSelection] | None = None
    ) -> torch.Tensor:
        """(B, M) residuals at ``full`` (B, P); the contour choice is made here if not given."""
        selections = selections or self.select(full)
        rows = torch.arange(full.shape[0], device=full.device)
        parts = [self.pose_residual(full, j, rows, selections[j]) for j in self.poses]
        parts.append(self.barrier_residual(full))
        return torch.cat(parts, 1)

    # ------------------------------------------------------------------------------------
    def jacobian(
        self, full: torch.Tensor, free: torch.Tensor, selections: dict[int, ContourSelection]
    ) -> torch.Tensor:
        """(B, M, F) Jacobian of :meth:`residual` w.r.t. the ``free`` (F,) parameters.

        Per pose, two autograd passes meet at the projected contour vertices:

        - forward mode gives the pixel tangents of the vertices that carry contour samples,
          for the tangents this pose depends on (the scales and its own parameters), folded
          into the batch dimension;
        - reverse mode gives the derivative of every residual entry w.r.t. the pixels of its
          own edge endpoints (each e_P entry depends on one edge, e_M on the sample edges).

        Their product is the Jacobian block.
        """
        b = full.shape[0]
        f = free.numel()
        m = self.residual_mask().shape[1]
        jac = torch.zeros(b, m, f, **self.kw)
        rows = torch.arange(b, device=full.device)
        scale_cols = (free < self.num_scale_params).nonzero().flatten()
        offset = 0
        for k, j in enumerate(self.poses):
            sel = selections[j]
            n_rows = self.person.valid[k].shape[1] + 1
            sl = self.pose_slices[j]
            pose_cols = ((free >= sl.start) & (free < sl.stop)).nonzero().flatten()
            cols = torch.cat([scale_cols, pose_cols])
            c = cols.numel()
            if c == 0:
                offset += n_rows
                continue
            ends, vidx, lookup = self._prepare(sel)
            # reverse mode: local derivatives of the residual entries w.r.t. endpoint pixels
            with torch.no_grad():
                pixels = self.pose_pixels(full, j, rows, vidx)
            pix = {
                n: v.detach().requires_grad_(True)
                for n, v in self._endpoint_pixels(pixels, lookup, ends).items()
            }
            with torch.enable_grad():
                e_p, e_m = self._pose_terms(k, rows, ends, sel, pix)
                grads = torch.autograd.grad(
                    e_p.sum() + e_m.sum(), list(pix.values()), allow_unused=True
                )
            local = {
                n: (g if g is not None else torch.zeros_like(pix[n]))
                for n, g in zip(pix, grads, strict=True)
            }
            # forward mode: pixel tangents of the contour vertices, c directions per subject
            rows_rep = rows.repeat_interleave(c)
            tangent = torch.zeros(b * c, full.shape[1], **self.kw)
            tangent[torch.arange(b * c), free[cols].repeat(b)] = 1.0
            with fwad.dual_level():
                dual = fwad.make_dual(full.repeat_interleave(c, dim=0), tangent)
                tan = fwad.unpack_dual(self.pose_pixels(dual, j, rows_rep, vidx)).tangent
            tan = tan.reshape(b, c, -1, 2).permute(0, 2, 1, 3)  # (B, K, c, 2)
            r = rows[:, None]
            t_of = {
                n: tan[r, lookup[getattr(ends, attr)]]
                for n, attr in (
                    ("pa", "person_a"),
                    ("pb", "person_b"),
                    ("ma", "model_a"),
                    ("mb", "model_b"),
                )
            }
            block_p = torch.einsum("bid,bicd->bic", local["pa"], t_of["pa"]) + torch.einsum(
                "bid,bicd->bic", local["pb"], t_of["pb"]
            )
            block_m = torch.einsum("bnd,bncd->bc", local["ma"], t_of["ma"]) + torch.einsum(
                "bnd,bncd->bc", local["mb"], t_of["mb"]
            )
            jac[:, offset : offset + n_rows - 1, cols] = block_p
            jac[:, offset + n_rows - 1, cols] = block_m
            offset += n_rows
        # barrier: elementwise, derivative weight * (-1 below, +1 above, 0 inside)
        x = full[:, free]
        lo, hi = self.lower[free], self.upper[free]
        slope = self.cfg.barrier_weight * ((x > hi).to(x) - (x < lo).to(x))
        jac[:, offset + free, torch.arange(f)] = slope
        return jac

    def solve_stage(
        self,
        full: torch.Tensor,
        stage: StageConfig,
        options,
        jacobian: str = "autograd",
        callback: Callable | None = None,
    ):
        """Run LM over one stage's free parameters; returns (full params (B, P), LMResult)."""
        from torchfit.solver import levenberg_marquardt

        free = self.stage_indices(stage)
        base = full.detach().clone()
        mask = self.residual_mask()
        cache: dict = {}

        def expand(x: torch.Tensor) -> torch.Tensor:
            reps = x.shape[0] // base.shape[0]
            onehot = torch.zeros(free.numel(), base.shape[1], **self.kw)
            onehot[torch.arange(free.numel()), free] = 1.0
            return base.repeat(reps, 1) * (1 - onehot.sum(0)) + x @ onehot

        def residual_fn(x: torch.Tensor):
            # the contour choice is held fixed while the solver tries steps, so every trial
            # is judged on the same smooth objective; it is refreshed at accepted points
            full_x = expand(x)
            if "sel" not in cache:
                cache["sel"] = self.select(full_x)
            reps = x.shape[0] // self.batch
            if reps == 1:
                return self.residual(full_x, cache["sel"]), mask
            out = [
                self.residual(full_x[i * self.batch : (i + 1) * self.batch], cache["sel"])
                for i in range(reps)
            ]
            return torch.cat(out), mask.repeat(reps, 1)

        def jacobian_fn(x: torch.Tensor):
            full_x = expand(x)
            cache["sel"] = self.select(full_x)
            jac = self.jacobian(full_x, free, cache["sel"])
            return jac, self.residual(full_x, cache["sel"])

        jac = jacobian_fn if jacobian == "autograd" else jacobian
        x0 = full[:, free].detach().clone()
        result = levenberg_marquardt(
            residual_fn, x0, options=options, jacobian=jac, callback=callback
        )
        out = full.detach().clone()
        out[:, free] = result.x
        return out, result


def person_data_from_masks(
    masks: torch.Tensor,
    camera: Camera,
    method: str = "chamfer",
    stride: int = 1,
    dtype: torch.dtype = torch.float64,
    uncertain: torch.Tensor | None = None,
    margin_px: int = 2,
) -> PersonData:
    """Person contours and distance maps from silhouettes.

    Args:
        masks: (B, J, H, W) bool silhouettes, J poses per subject.
        camera: B cameras.
        method: distance transform, ``"chamfer"`` (the paper's 3-4) or ``"euclidean"``.
        stride: keep every ``stride``-th contour pixel.
        uncertain: optional (B, J, H, W) bool, pixels where the silhouette is not to be
            trusted (:attr:`torchfit.image.SegmentationResult.shadow`): person contour
            pixels within ``margin_px`` of one do not count in e_P, and model contour points
            on one do not count in e_M. A silhouette cut short where a foot or shin looked
            like its own shadow then neither pulls the model's feet up nor pushes the model
            back (the floor contact would turn that into a taller body).
        margin_px: see ``uncertain``.

    Returns:
        :class:`PersonData`; an empty silhouette gives an empty contour and a map of large
        constant distance (that pose then only constrains through e_M).
    """
    b, n_pose, h, w = masks.shape
    near = None
    if uncertain is not None:
        if uncertain.shape != masks.shape:
            raise ShapeError(
                f"uncertain: expected the shape of masks {tuple(masks.shape)}, "
                f"got {tuple(uncertain.shape)}"
            )
        k_size = 2 * margin_px + 1
        near = torch.nn.functional.max_pool2d(
            uncertain.float(), k_size, stride=1, padding=margin_px
        ).bool()
    contours, valid, maps = [], [], []
    for k in range(n_pose):
        traced = [trace_outer_contour(masks[i, k])[::stride] for i in range(b)]
        n = max(1, max(len(c) for c in traced))
        pts = torch.zeros(b, n, 2, dtype=dtype)
        ok = torch.zeros(b, n, dtype=torch.bool)
        for i, c in enumerate(traced):
            pts[i, : len(c)] = c.to(dtype)
            ok[i, : len(c)] = True
            if near is not None and len(c):
                c = c.long()
                ok[i, : len(c)] &= ~near[i, k, c[:, 1], c[:, 0]]
        contours.append(pts)
        valid.append(ok)
        dmap = mask_to_distance_map(masks[:, k : k + 1], method)[:, 0].to(dtype)
        maps.append(torch.nan_to_num(dmap, posinf=float(h + w)))
    flags = None if uncertain is None else [uncertain[:, k] for k in range(n_pose)]
    return PersonData(contours, valid, maps, camera, flags)
