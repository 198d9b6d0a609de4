"""The posed body's derivatives in closed form (:class:`ClosedFormDerivatives`, a part of
:class:`torchfit.body.model.BodyModel`): w.r.t. the pose (:meth:`~ClosedFormDerivatives.
pose_jacobian`, the tracker's) and w.r.t. the scales and joint angles
(:meth:`~ClosedFormDerivatives.jacobian`, the fit's), from one kinematics pass each
(:meth:`~ClosedFormDerivatives.pose_pass`, which a caller may hand back)."""

from __future__ import annotations

import torch

from torchfit.body.output import BodyOutput
from torchfit.body.rotations import axis_angle_to_matrix, cross_matrix, left_jacobian
from torchfit.errors import check_shape

__all__ = ["ClosedFormDerivatives"]


class ClosedFormDerivatives:
    """The derivative methods of :class:`torchfit.body.model.BodyModel` (its chain, its
    vertices' segments and its ``_posed_frames`` pass)."""

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
