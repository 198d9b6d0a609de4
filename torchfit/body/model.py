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

import torch

from torchfit._dual import is_dual, lift
from torchfit.body.derivatives import ClosedFormDerivatives
from torchfit.body.kinematics import SkeletonChain
from torchfit.body.output import BodyOutput
from torchfit.body.rotations import axis_angle_to_matrix
from torchfit.body.template import Template, load_template
from torchfit.errors import ModelError, check_shape

__all__ = ["BodyModel", "BodyOutput", "axis_angle_to_matrix"]


class BodyModel(ClosedFormDerivatives, torch.nn.Module):
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
