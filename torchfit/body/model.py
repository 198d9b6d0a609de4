"""The stateless, batched, differentiable body model.

    scales (B, S, 3), joint_angles (B, Q), root_translation (B, 3), root_rotation (B, 3)
        -> posed vertices (B, V, 3), segment origins (B, S, 3), rotations (B, S, 3, 3)

Segment i with scale σ_i = (σx, σy, σz) scales its mesh in its own frame about its origin
(the proximal joint centre) and moves its child joints with it: a child's origin is
``p_child = p_i + R_i (σ_i ⊙ o_child)`` where ``o_child`` is the template offset in segment
i's frame. The root segment's frame is placed at ``root_translation`` with the axis-angle
``root_rotation`` (world frame, radians). Metres throughout; world frame z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchfit._dual import is_dual, lift
from torchfit.body.kinematics import SkeletonChain
from torchfit.body.rotations import axis_angle_to_matrix, cross_matrix, left_jacobian
from torchfit.body.template import Template, load_template
from torchfit.errors import ModelError, check_shape

__all__ = ["BodyModel", "BodyOutput", "axis_angle_to_matrix"]


@dataclass
class BodyOutput:
    """A posed body.

    Attributes:
        vertices: (B, V, 3) world coordinates, metres.
        origins: (B, S, 3) segment origins (joint centres) in the world frame.
        rotations: (B, S, 3, 3) segment frame rotations in the world frame.
    """

    vertices: torch.Tensor
    origins: torch.Tensor
    rotations: torch.Tensor

    @property
    def transforms(self) -> torch.Tensor:
        """(B, S, 4, 4) homogeneous segment-to-world transforms."""
        b, s = self.origins.shape[:2]
        t = torch.zeros(b, s, 4, 4, dtype=self.origins.dtype, device=self.origins.device)
        t[..., :3, :3] = self.rotations
        t[..., :3, 3] = self.origins
        t[..., 3, 3] = 1
        return t


class BodyModel(torch.nn.Module):
    """A template made posable: stateless forward, batched over subjects.

    A ``torch.nn.Module`` without parameters: the tensors that define the model (mesh
    vertices, faces, segment offsets, joint axes and limits, the segment-to-group map, ...)
    are non-persistent buffers, so ``model.to(device, dtype)`` moves and casts it and
    :attr:`device` / :attr:`dtype` follow.

    Args:
        template: a :class:`Template` or a template name / URDF path.
        device: where the tensors live.
        dtype: float dtype (float64 for Jacobian checks, float32 for speed).
    """

    def __init__(
        self,
        template: Template | str,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.template = template if isinstance(template, Template) else load_template(template)
        t = self.template
        # built in float64 on the CPU (the segment offsets are measured on the chain), then
        # moved and cast with everything else at the end
        self.chain = SkeletonChain(t.urdf, t.segments, t.parents, str(t.urdf_path))
        self.dof_names = self.chain.dof_names
        # mesh vertices padded per segment: (S, Vmax, 3) plus the flat index back to (V,)
        counts = torch.bincount(t.vertex_segment, minlength=t.num_segments)
        vmax = int(counts.max())
        padded = torch.zeros(t.num_segments, vmax, 3, dtype=torch.float64)
        slot = torch.cat([torch.arange(int(c)) for c in counts])
        padded[t.vertex_segment, slot] = t.vertices.to(torch.float64)
        self.register_buffer("_padded", padded, persistent=False)
        self.register_buffer("_flat_index", t.vertex_segment * vmax + slot, persistent=False)
        self.register_buffer("_vertices", t.vertices.to(torch.float64), persistent=False)
        self.register_buffer("_vertex_segment", t.vertex_segment.clone(), persistent=False)
        self.register_buffer("_segment_group", t.segment_group.clone(), persistent=False)
        self.register_buffer("faces", t.faces.clone(), persistent=False)
        # tree levels for the position pass (parents first): per level, the segments and their
        # parents as index buffers ``_level{d}``, ``_level{d}_parents`` and as Python
        # (segment, parent) pairs for the per-segment loop
        depth = [0] * t.num_segments
        for s, p in enumerate(t.parents):
            depth[s] = 0 if p < 0 else depth[p] + 1
        self._levels: list[list[tuple[int, int]]] = []
        for d in range(1, max(depth) + 1):
            pairs = [(s, int(t.parents[s])) for s in range(t.num_segments) if depth[s] == d]
            self._levels.append(pairs)
            segs, pars = zip(*pairs, strict=True)
            self.register_buffer(f"_level{d}", torch.tensor(segs), persistent=False)
            self.register_buffer(f"_level{d}_parents", torch.tensor(pars), persistent=False)
        # scale levers: a point of segment s moves with segment s's scale σ_i along its frame's
        # axis i by its own local coordinate, and with an ancestor a's scale by the offset of
        # the next segment down the path to s (see :meth:`jacobian`). Per segment, the path
        # up to the root (itself first, padded with itself and a zero lever): ``_path`` (S, D)
        # and ``_path_levers`` (S, D, 3), slot 0 filled per vertex
        paths: list[list[int]] = []
        path_levers = []
        offsets = self.chain.offsets.to(torch.float64)
        for s in range(t.num_segments):
            path, levers = [s], [torch.zeros(3, dtype=torch.float64)]
            child, par = s, int(t.parents[s])
            while par >= 0:
                path.append(par)
                levers.append(offsets[child])
                child, par = par, int(t.parents[par])
            paths.append(path)
            path_levers.append(levers)
        depth = max(len(p) for p in paths)
        path_t = torch.tensor([p + [p[0]] * (depth - len(p)) for p in paths])
        zero = torch.zeros(3, dtype=torch.float64)
        lever_t = torch.stack([torch.stack(lv + [zero] * (depth - len(lv))) for lv in path_levers])
        self.register_buffer("_path", path_t, persistent=False)
        self.register_buffer("_path_levers", lever_t, persistent=False)
        self.to(device=device, dtype=dtype)

    # ----------------------------------------------------------------------------------------
    @property
    def dtype(self) -> torch.dtype:
        """Float dtype of the model's buffers (follows ``.to``)."""
        return self._padded.dtype

    @property
    def device(self) -> torch.device:
        """Device of the model's buffers (follows ``.to``)."""
        return self._padded.device

    @property
    def joint_lower(self) -> torch.Tensor:
        """(Q,) lower joint limits from the URDF, radians."""
        return self.chain.lower

    @property
    def joint_upper(self) -> torch.Tensor:
        """(Q,) upper joint limits from the URDF, radians."""
        return self.chain.upper

    @property
    def offsets(self) -> torch.Tensor:
        """(S, 3) template origin of each segment in its parent segment's frame."""
        return self.chain.offsets

    # ----------------------------------------------------------------------------------------
    @property
    def num_segments(self) -> int:
        """S, the number of segments."""
        return self.template.num_segments

    @property
    def num_dofs(self) -> int:
        """Q, the number of joint DOFs."""
        return len(self.dof_names)

    @property
    def num_groups(self) -> int:
        """G, the number of scale groups."""
        return len(self.template.scale_groups)

    def dof_index(self, name: str) -> int:
        """Index of joint DOF ``name`` in the joint-angle vector."""
        try:
            return self.dof_names.index(name)
        except ValueError:
            raise ModelError(f"template {self.template.name!r} has no joint DOF {name!r}") from None

    def zeros(self, batch: int) -> dict[str, torch.Tensor]:
        """Neutral parameters: unit scales, zero angles, root at the origin."""
        kw = {"dtype": self.dtype, "device": self.device}
        return {
            "scales": torch.ones(batch, self.num_segments, 3, **kw),
            "joint_angles": torch.zeros(batch, self.num_dofs, **kw),
            "root_translation": torch.zeros(batch, 3, **kw),
            "root_rotation": torch.zeros(batch, 3, **kw),
        }

    def expand_scales(self, group_scales: torch.Tensor) -> torch.Tensor:
        """Map free scales per group to all segments (left/right symmetry, spine coupling).

        Args:
            group_scales: (B, G, 3), groups as ``template.scale_groups``.

        Returns:
            (B, S, 3) per-segment scales.
        """
        check_shape("group_scales", group_scales, ("B", self.num_groups, 3))
        return group_scales[:, self._segment_group.to(group_scales.device)]

    # ----------------------------------------------------------------------------------------
    def forward(
        self,
        scales: torch.Tensor,
        joint_angles: torch.Tensor,
        root_translation: torch.Tensor,
        root_rotation: torch.Tensor,
        vertex_index: torch.Tensor | None = None,
    ) -> BodyOutput:
        """Pose the scaled template.

        Args:
            scales: (B, S, 3) per-segment scales in each segment's frame (1 = template).
            joint_angles: (B, Q) radians, order :attr:`dof_names`.
            root_translation: (B, 3) world position of the root segment origin, metres.
            root_rotation: (B, 3) axis-angle of the root frame in the world, radians, or
                (B, 3, 3) rotation matrices.
            vertex_index: optional (K,) template vertex indices; only those are posed and
                ``vertices`` is (B, K, 3) (cheaper when few vertices are needed).

        Returns:
            :class:`BodyOutput` with (B, V, 3) vertices, (B, S, 3) origins and
            (B, S, 3, 3) rotations.
        """
        b = scales.shape[0] if scales.dim() == 3 else -1
        check_shape("scales", scales, (b, self.num_segments, 3))
        check_shape("joint_angles", joint_angles, (b, self.num_dofs))
        check_shape("root_translation", root_translation, (b, 3))
        dual = any(is_dual(t) for t in (scales, joint_angles, root_translation, root_rotation))
        if root_rotation.dim() == 3:
            check_shape("root_rotation", root_rotation, (b, 3, 3))
            rot_root = root_rotation
        else:
            check_shape("root_rotation", root_rotation, (b, 3))
            rot_root = axis_angle_to_matrix(root_rotation)  # (B, 3, 3)
        rot = rot_root[:, None] @ self.chain.rotations(joint_angles)  # (B, S, 3, 3)
        return self._posed(scales, rot, root_translation, vertex_index, dual)

    def _posed(
        self,
        scales: torch.Tensor,
        rot: torch.Tensor,
        root_translation: torch.Tensor,
        vertex_index: torch.Tensor | None,
        dual: bool,
    ) -> BodyOutput:
        """Origins and vertices from the segments' world rotations (B, S, 3, 3)."""
        offsets = lift(self.offsets, dual)
        # positions, level by level: p_c = p_parent + R_parent (σ_parent ⊙ o_c)
        origins = [None] * self.num_segments
        origins[0] = root_translation
        for d, pairs in enumerate(self._levels, 1):
            level, par = getattr(self, f"_level{d}"), getattr(self, f"_level{d}_parents")
            step = (rot[:, par] @ (scales[:, par] * offsets[level])[..., None])[..., 0]
            for k, (s, p) in enumerate(pairs):
                origins[s] = origins[p] + step[:, k]
        origins_t = torch.stack(origins, dim=1)  # (B, S, 3)

        if vertex_index is not None:
            vertices = self._placed(scales, rot, origins_t, vertex_index, dual)
            return BodyOutput(vertices=vertices, origins=origins_t, rotations=rot)
        local = scales[:, :, None, :] * lift(self._padded, dual)  # (B, S, Vmax, 3)
        posed = torch.einsum("bsij,bsvj->bsvi", rot, local) + origins_t[:, :, None, :]
        vertices = posed.reshape(posed.shape[0], -1, 3)[:, self._flat_index]
        return BodyOutput(vertices=vertices, origins=origins_t, rotations=rot)

    def _placed(
        self,
        scales: torch.Tensor,
        rot: torch.Tensor,
        origins: torch.Tensor,
        vertex_index: torch.Tensor,
        dual: bool,
    ) -> torch.Tensor:
        """(B, K, 3) the vertices ``vertex_index`` (K,) of segments posed by their world
        rotations ``rot`` (B, S, 3, 3) and origins (B, S, 3)."""
        seg = self._vertex_segment.to(vertex_index.device)[vertex_index]
        local = scales[:, seg] * lift(self._vertices[vertex_index], dual)  # (B, K, 3)
        return (rot[:, seg] @ local[..., None])[..., 0] + origins[:, seg]

    def _posed_frames(
        self,
        scales: torch.Tensor,
        joint_angles: torch.Tensor,
        root_translation: torch.Tensor,
        rot_root: torch.Tensor,
        vertex_index: torch.Tensor,
    ) -> tuple[torch.Tensor, BodyOutput, torch.Tensor]:
        """One kinematics pass for the closed-form derivatives: every chain frame's rotation
        (B, F, 3, 3) in the root frame, the posed points ``vertex_index`` (K,) under the root
        rotation matrices ``rot_root`` (B, 3, 3), and each point's segment (K,)."""
        check_shape("scales", scales, ("B", self.num_segments, 3))
        frames = self.chain.frame_rotations(joint_angles)
        rot = rot_root[:, None] @ frames[:, self.chain.frame_indices]
        out = self._posed(scales, rot, root_translation, vertex_index, False)
        return frames, out, self._vertex_segment.to(vertex_index.device)[vertex_index]

    def _turns(
        self,
        rot_root: torch.Tensor,
        frames: torch.Tensor,
        out: BodyOutput,
        seg: torch.Tensor,
        dofs: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """(B, Q', 3, K) ``∂p/∂q_k = a_k × (p − c_k)`` of posed points ``out.vertices`` (B, K, 3)
        of segments ``seg`` (K,) for the DOFs ``dofs`` (Q',) (default: all), zero where DOF k
        does not move the point."""
        chain = self.chain
        p = out.vertices
        dof_frames, dof_axes = chain.dof_frames, chain.axes
        dof_pivot, dof_moves = chain.dof_pivot, chain.dof_moves
        if dofs is not None:
            dof_frames, dof_axes = dof_frames[dofs], dof_axes[dofs]
            dof_pivot, dof_moves = dof_pivot[dofs], dof_moves[dofs]
        dof_rot = rot_root[:, None] @ frames[:, dof_frames]  # (B, Q', 3, 3)
        axes = (dof_rot @ dof_axes[..., None])[..., 0]  # (B, Q', 3) world axes
        pivots = out.origins[:, dof_pivot]  # (B, Q', 3)
        # elementwise, for the (DOF, point) pairs where the DOF moves the point only (a batched
        # product would round a row by its batch)
        k, i = dof_moves[:, seg].nonzero().unbind(1)
        turn = torch.linalg.cross(axes[:, k], p[:, i] - pivots[:, k])  # (B, n, 3)
        full = p.new_zeros(p.shape[0], len(dof_pivot), p.shape[1], 3)
        full[:, k, i] = turn
        return full.transpose(2, 3)

    def pose_pass(
        self,
        scales: torch.Tensor,
        joint_angles: torch.Tensor,
        root_translation: torch.Tensor,
        root_rotation: torch.Tensor,
        vertex_index: torch.Tensor,
    ) -> tuple:
        """The kinematics pass of :meth:`pose_jacobian` alone (arguments as there): a tuple
        whose third item is the posed :class:`BodyOutput` (its vertices as :meth:`forward`
        gives them). Handed back to :meth:`pose_jacobian` at the same pose, it spares the
        pass: a solver that evaluates its residual at a point and then, once the step is
        accepted, the Jacobian there, poses the body once."""
        check_shape("root_rotation", root_rotation, ("B", 3))
        rot_root = axis_angle_to_matrix(root_rotation)
        passed = self._posed_frames(scales, joint_angles, root_translation, rot_root, vertex_index)
        return (rot_root, *passed)

    def repose(self, passed: tuple, scales: torch.Tensor, vertex_index: torch.Tensor) -> tuple:
        """The :meth:`pose_pass` of other vertices ``vertex_index`` at the pose of ``passed``
        (a pose pass with these ``scales``): its chain frames, rotations and origins are kept,
        only the vertices are posed, as a pose pass there would pose them."""
        rot_root, frames, out, _ = passed
        vertices = self._placed(scales, out.rotations, out.origins, vertex_index, False)
        seg = self._vertex_segment.to(vertex_index.device)[vertex_index]
        return rot_root, frames, BodyOutput(vertices, out.origins, out.rotations), seg

    def pose_jacobian(
        self,
        scales: torch.Tensor,
        joint_angles: torch.Tensor,
        root_translation: torch.Tensor,
        root_rotation: torch.Tensor,
        vertex_index: torch.Tensor,
        passed: tuple | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed vertices and their derivatives w.r.t. the pose, in closed form.

        The segments are rigid, so a joint DOF k turns every point it moves about its world
        axis ``a_k`` through its pivot ``c_k`` (the origin of the segment it ends in):
        ``∂p/∂q_k = a_k × (p − c_k)``. The root translation moves every point by itself, and
        the root's axis-angle ``r`` turns them about the root origin ``t``:
        ``∂p/∂r = −[p − t]× J_l(r)``, with ``J_l`` the left Jacobian of SO(3)
        (``Exp(r + δ) ≈ Exp(J_l(r) δ) Exp(r)``). One forward pass instead of one per
        parameter (forward differences) or per tangent direction (forward-mode AD).

        Args:
            scales, joint_angles, root_translation: as :meth:`forward`.
            root_rotation: (B, 3) axis-angle (the derivative is w.r.t. it).
            vertex_index: (K,) template vertices to pose.
            passed: :meth:`pose_pass` of these same arguments, if the caller has it.

        Returns:
            (B, K, 3) vertices (as :meth:`forward` gives them) and (B, K, 3, 6 + Q) their
            Jacobian w.r.t. ``[root_translation, root_rotation, joint_angles]``.
        """
        if passed is None:
            passed = self.pose_pass(
                scales, joint_angles, root_translation, root_rotation, vertex_index
            )
        rot_root, frames, out, seg = passed
        p = out.vertices  # (B, K, 3)
        b, k = p.shape[:2]
        q = self.num_dofs
        jac = torch.zeros(b, 3, 6 + q, k, dtype=p.dtype, device=p.device)
        jac[:, [0, 1, 2], [0, 1, 2]] = 1.0
        jac[:, :, 6:] = self._turns(rot_root, frames, out, seg).transpose(1, 2)
        # root rotation: column c is J_l[:, c] × (p − t)
        left = left_jacobian(root_rotation)  # (B, 3, 3)
        rel = (p - root_translation[:, None]).transpose(1, 2)  # (B, 3, K)
        cols = cross_matrix(left.transpose(1, 2))  # (B, 3, 3, 3): [J_l[:, c]]×
        jac[:, :, 3:6] = (cols @ rel[:, None]).transpose(1, 2)
        return p, jac.permute(0, 3, 1, 2)

    def jacobian(
        self,
        scales: torch.Tensor,
        joint_angles: torch.Tensor,
        root_translation: torch.Tensor,
        root_rotation: torch.Tensor,
        vertex_index: torch.Tensor,
        dofs: torch.Tensor | None = None,
        groups: torch.Tensor | None = None,
    ) -> tuple[BodyOutput, torch.Tensor, torch.Tensor]:
        """Posed vertices and their derivatives w.r.t. the scales and the joint angles, in
        closed form (the root held; a caller adds its own root parametrisation, which turns
        every point about the root origin).

        A point of segment s is ``p = o_s + R_s (σ_s ⊙ v)``, and each ancestor a adds
        ``R_a (σ_a ⊙ o_c)`` to ``o_s``, with ``o_c`` the template offset of the next segment c
        on the path down to s. So ``∂p/∂σ_{a,i} = R_a[:, i] w_i``, the lever ``w`` being
        ``v`` for s itself, ``o_c`` for an ancestor, and 0 otherwise; and
        ``∂p/∂q_k = a_k × (p − c_k)`` as in :meth:`pose_jacobian`. Every product is
        elementwise or a fixed-size small matrix product per row, and the sums over the
        segments of a group run in a fixed order, so a row's numbers do not depend on the
        batch around it.

        Args:
            scales, joint_angles, root_translation: as :meth:`forward`.
            root_rotation: (B, 3, 3) root rotation matrices.
            vertex_index: (K,) template vertices to pose.
            dofs: (Q',) the joint DOFs wanted (default: all Q).
            groups: (S,) the scale group of each segment, G groups (the derivative w.r.t. a
                group's scale sums its segments'; default: each segment its own group).

        Returns:
            the posed body (vertices (B, K, 3)), ``∂p/∂σ`` (B, K, 3, G, 3) w.r.t. each group's
            three scales, and ``∂p/∂q`` (B, K, 3, Q').
        """
        check_shape("root_rotation", root_rotation, ("B", 3, 3))
        frames, out, seg = self._posed_frames(
            scales, joint_angles, root_translation, root_rotation, vertex_index
        )
        rot = out.rotations  # (B, S, 3, 3)
        b, k = out.vertices.shape[:2]
        path = self._path[seg]  # (K, D): the segment, its parent, ... (padded)
        levers = self._path_levers[seg]  # (K, D, 3)
        levers[:, 0] = self._vertices[vertex_index]
        if groups is None:
            groups = torch.arange(self.num_segments, device=seg.device)
        g = int(groups.max()) + 1
        d = path.shape[1]
        # (B, K, D, 3, 3): R_a[:, i] w_i along each point's path, then summed into its groups
        along = rot[:, path] * levers[None, :, :, None, :]
        target = (groups[path][..., None] * 3 + torch.arange(3, device=seg.device)).reshape(k, -1)
        d_scales = torch.zeros(b, k, 3, g * 3, dtype=along.dtype, device=along.device)
        src = along.permute(0, 1, 3, 2, 4).reshape(b, k, 3, d * 3)
        d_scales.scatter_add_(3, target[None, :, None].expand(b, -1, 3, -1), src)
        d_joints = self._turns(root_rotation, frames, out, seg, dofs).permute(0, 3, 2, 1)
        return out, d_scales.reshape(b, k, 3, g, 3), d_joints

    def joint_positions(self, out: BodyOutput) -> dict[str, torch.Tensor]:
        """Named joint centres (design.md section 3 names) of a posed body.

        Returns:
            name -> (B, 3): the template's measurement joints, ``back`` (midpoint of the hips)
            and the landmarks (``head_top``, fingertips, soles, …).
        """
        t = self.template
        joints = {name: out.origins[:, s] for name, s in t.joints.items()}
        if "l_hip" in joints and "r_hip" in joints:
            joints["back"] = 0.5 * (joints["l_hip"] + joints["r_hip"])
        for name, v in t.landmarks.items():
            joints[name] = out.vertices[:, v]
        return joints
