"""The skeleton as a pytorch-kinematics chain (the only importer of pytorch_kinematics).

The chain gives the world rotation of every segment frame for a batch of joint angles. Segment
positions are composed separately (:mod:`torchfit.body.model`) because segment scales change
the joint offsets per subject, which a chain with fixed URDF offsets cannot express; rotations
do not depend on those offsets.

pytorch-kinematics parses the URDF and owns the tree and the forward-kinematics pass
(``Chain.forward_kinematics_tensor``, called with its plain-autograd path
``analytical_grad=False`` so that reverse- and forward-mode AD both flow through it; it writes
its transforms in place and does not run under ``torch.func.vmap``). The chain's constants —
the joint axes and the static frame offsets — are read once through its public API (the
frames' ``joint.axis``, ``joint.offset`` and ``link.offset``) into buffers of
:class:`SkeletonChain`, so they follow ``Module.to`` like the rest of the body model.

One private use of pytorch-kinematics remains, in :func:`_forward_kinematics` alone: the
forward pass reads its constants from the chain's ``axes`` and ``_static_offsets`` attributes,
and no public argument passes them in. Under forward-mode AD those constants must be dual
tensors (zero tangent): pytorch-kinematics' public call with its plain constants and dual
joint angles gives the same numbers bit for bit but costs about 3.5 ms more per call on the
CPU (mixed dual/plain arithmetic, see :mod:`torchfit._dual`): 2-3x the forward kinematics of
up to ~100 rows, ~20 % of a 64-row model call; the gap closes towards ~1000 rows.
``tests/body/test_kinematics_contract.py`` pins those attributes against the public API and
fails on an upgrade that changes them.
"""

from __future__ import annotations

import logging
import warnings

import numpy as np
import torch

from torchfit._dual import is_dual, lift
from torchfit.errors import ModelError, check_shape

__all__ = ["SkeletonChain", "TESTED_PK_VERSION"]

log = logging.getLogger(__name__)

#: The pytorch-kinematics version whose internals :func:`_forward_kinematics` was checked
#: against (``tests/body/test_kinematics_contract.py``).
TESTED_PK_VERSION = "0.10.0"


def _forward_kinematics(
    chain, joint_angles: torch.Tensor, axes: torch.Tensor, static_offsets: torch.Tensor
) -> torch.Tensor:
    """pytorch-kinematics' forward kinematics with the chain's constants supplied by the caller.

    The one place where torchfit touches pytorch-kinematics internals: ``Chain``'s forward
    pass reads the joint axes from ``chain.axes`` (n_joints, 3) and the per-frame static
    offsets (link offset @ joint offset) from ``chain._static_offsets`` (num_frames, 4, 4).
    They are swapped for ``axes`` and ``static_offsets`` (in the dtype of ``joint_angles``,
    dual tensors under forward-mode AD) for the duration of the call and then restored (so
    one chain must not run in two threads at once).

    Args:
        chain: a ``pytorch_kinematics.Chain`` whose index tensors are on the device of
            ``joint_angles``.
        joint_angles: (B, n_joints).
        axes: (n_joints, 3) joint axes, order ``chain.get_joint_parameter_names()``.
        static_offsets: (num_frames, 4, 4), frames in ``chain.frame_to_idx`` order.

    Returns:
        (num_frames, B, 4, 4) frame-to-root transforms.
    """
    try:
        saved = chain.axes, chain._static_offsets
    except AttributeError as exc:
        from importlib.metadata import version

        raise ModelError(
            f"pytorch-kinematics {version('pytorch-kinematics')} has no Chain.axes / "
            f"Chain._static_offsets, which torchfit (checked against {TESTED_PK_VERSION}) "
            "swaps; see tests/body/test_kinematics_contract.py"
        ) from exc
    chain.axes, chain._static_offsets = axes, static_offsets
    try:
        return chain.forward_kinematics_tensor(joint_angles, analytical_grad=False)
    finally:
        chain.axes, chain._static_offsets = saved


def chain_constants(chain) -> tuple[torch.Tensor, torch.Tensor]:
    """Joint axes and static frame offsets of a pytorch-kinematics chain, from its public API.

    Returns:
        (n_joints, 3) unit joint axes in ``chain.get_joint_parameter_names()`` order and
        (num_frames, 4, 4) link offset @ joint offset per frame (identity where absent), in
        ``chain.frame_to_idx`` order — what the chain's forward pass composes with the joint
        rotations. Both in the chain's dtype.
    """
    names = chain.get_frame_names(exclude_fixed=False)
    index = chain.get_frame_indices(*names).tolist()
    eye = torch.eye(4, dtype=chain.dtype, device=chain.device)[None]
    static: list[torch.Tensor | None] = [None] * len(names)
    for name, i in zip(names, index, strict=True):
        frame = chain.find_frame(name)
        lo = eye if frame.link.offset is None else frame.link.offset.get_matrix()
        jo = eye if frame.joint.offset is None else frame.joint.offset.get_matrix()
        static[i] = (lo @ jo).squeeze(0)
    joints = {j.name: j for j in chain.get_joints()}
    axes = [joints[n].axis for n in chain.get_joint_parameter_names()]
    return torch.stack(axes), torch.stack(static)


class SkeletonChain(torch.nn.Module):
    """Joint angles (B, Q) -> segment rotations (B, S, 3, 3) and zero-pose offsets.

    Buffers (they follow ``.to(device, dtype)``): ``axes`` (Q, 3) and ``static_offsets``
    (F, 4, 4), the chain's constants; ``lower`` / ``upper`` (Q,) joint limits from the URDF;
    ``offsets`` (S, 3) segment origins in their parent's frame; ``frame_indices`` (S,).

    Args:
        urdf: URDF text.
        segments: S link names whose frames are wanted (parents first).
        parents: (S,) parent segment index (-1 for the root).
        source: name used in error messages.
        dtype: float dtype of the chain.
    """

    def __init__(
        self,
        urdf: str,
        segments: list[str],
        parents: np.ndarray,
        source: str = "<urdf>",
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        import pytorch_kinematics as pk

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                chain = pk.build_chain_from_urdf(urdf)
        except Exception as exc:  # the URDF parser raises assorted types
            raise ModelError(f"{source}: pytorch-kinematics cannot load the URDF: {exc}") from exc
        self.chain = chain  # its index tensors follow the buffers' device (see _apply)
        self.dof_names: list[str] = list(chain.get_joint_parameter_names())
        frame_names = set(chain.get_frame_names(exclude_fixed=False))
        frames = []
        for seg in segments:
            name = seg if seg in frame_names else f"{seg}_frame"
            if name not in frame_names:
                raise ModelError(f"{source}: link {seg!r} missing from the kinematic chain")
            frames.append(name)
        axes, static = chain_constants(chain)
        lower, upper = chain.get_joint_limits()
        self.register_buffer("axes", axes.to(dtype), persistent=False)
        self.register_buffer("static_offsets", static.to(dtype), persistent=False)
        self.register_buffer("lower", torch.as_tensor(np.asarray(lower), dtype=dtype), False)
        self.register_buffer("upper", torch.as_tensor(np.asarray(upper), dtype=dtype), False)
        self.register_buffer("frame_indices", chain.get_frame_indices(*frames).clone(), False)
        self.parents = np.asarray(parents)
        self.register_buffer("offsets", self._segment_offsets(source), persistent=False)
        dof_frames, pivots, moves = self._dof_structure(frames, source)
        self.register_buffer("dof_frames", dof_frames, persistent=False)
        self.register_buffer("dof_pivot", pivots, persistent=False)
        self.register_buffer("dof_moves", moves, persistent=False)

    @property
    def num_dofs(self) -> int:
        """Q, the number of joint DOFs."""
        return len(self.dof_names)

    def _apply(self, fn, recurse: bool = True):
        super()._apply(fn, recurse)
        # pytorch-kinematics' own index tensors (its float constants are not used, see
        # _forward_kinematics) go where the buffers went
        if torch.device(self.chain.device) != self.axes.device:
            self.chain = self.chain.to(device=self.axes.device)
        return self

    def _all_transforms(self, joint_angles: torch.Tensor) -> torch.Tensor:
        # (num_frames, B, 4, 4); under forward mode the constants are lifted to zero-tangent
        # duals (mixed dual/plain arithmetic is slow)
        dual = is_dual(joint_angles)
        return _forward_kinematics(
            self.chain, joint_angles, lift(self.axes, dual), lift(self.static_offsets, dual)
        )

    def _transforms(self, joint_angles: torch.Tensor) -> torch.Tensor:
        # segment frames (B, S, 4, 4)
        return self._all_transforms(joint_angles)[self.frame_indices].transpose(0, 1)

    def _dof_structure(
        self, frames: list[str], source: str
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Where each DOF sits in the tree: its frame, its pivot segment, what it moves.

        Returns:
            ``dof_frames`` (Q,) the chain frame index whose joint is the DOF; ``dof_pivot``
            (Q,) the segment whose origin the DOF turns about (the first segment frame at or
            below it: a DOF's frame carries no translation of its own, see
            :meth:`_segment_offsets`); ``dof_moves`` (Q, S) bool, DOF k turns segment s.
        """
        segment_of = {name: s for s, name in enumerate(frames)}
        dof = {name: k for k, name in enumerate(self.dof_names)}
        q, s_count = len(self.dof_names), len(frames)
        dof_frames = torch.full((q,), -1, dtype=torch.long)
        pivots = torch.full((q,), -1, dtype=torch.long)
        moves = torch.zeros(q, s_count, dtype=torch.bool)
        pending: list[int] = []  # DOFs on the path whose pivot segment is not reached yet
        stack = [(self.chain.find_frame(frames[0]), [], [])]
        while stack:
            frame, above, open_dofs = stack.pop()
            here, waiting = list(above), list(open_dofs)
            k = dof.get(frame.joint.name) if frame.joint.joint_type != "fixed" else None
            if k is not None:
                dof_frames[k] = int(self.chain.get_frame_indices(frame.name)[0])
                here.append(k)
                waiting.append(k)
            s = segment_of.get(frame.name)
            if s is not None:
                moves[here, s] = True
                pivots[waiting] = s
                waiting = []
            pending.extend(waiting if not frame.children else [])
            for child in frame.children:
                stack.append((child, here, waiting))
        missing = [self.dof_names[k] for k in range(q) if int(pivots[k]) < 0]
        if missing or pending:
            raise ModelError(
                f"{source}: joint DOFs {missing or pending} do not lead to a segment below "
                "the root segment"
            )
        return dof_frames, pivots, moves

    def frame_rotations(self, joint_angles: torch.Tensor) -> torch.Tensor:
        """(B, F, 3, 3) rotation of every chain frame (segments and DOF frames) in the root
        frame."""
        check_shape("joint_angles", joint_angles, ("B", self.num_dofs))
        return self._all_transforms(joint_angles)[..., :3, :3].transpose(0, 1)

    def _segment_offsets(self, source: str) -> torch.Tensor:
        """(S, 3) origin of each segment in its parent's frame; checks it is pose-independent."""
        dtype = self.axes.dtype
        probe = torch.zeros(2, self.num_dofs, dtype=dtype)
        gen = torch.Generator().manual_seed(0)
        probe[1] = self.lower + (self.upper - self.lower) * torch.rand(
            self.num_dofs, generator=gen, dtype=dtype
        )
        t = self._transforms(probe)
        offsets = torch.zeros(len(self.parents), 3, dtype=dtype)
        for s, p in enumerate(self.parents):
            if p < 0:
                continue
            rel = t[:, p, :3, :3].transpose(-1, -2) @ (t[:, s, :3, 3] - t[:, p, :3, 3])[..., None]
            rel = rel[..., 0]
            if not torch.allclose(rel[0], rel[1], atol=1e-9):
                raise ModelError(
                    f"{source}: the offset of segment {s} from its parent changes with the joint "
                    "angles; put the translation on the first joint out of the parent segment"
                )
            offsets[s] = rel[0]
        return offsets

    def rotations(self, joint_angles: torch.Tensor) -> torch.Tensor:
        """Segment rotations relative to the root frame.

        Args:
            joint_angles: (B, Q) radians, order :attr:`dof_names`.

        Returns:
            (B, S, 3, 3) rotation of each segment frame in the root frame.
        """
        check_shape("joint_angles", joint_angles, ("B", self.num_dofs))
        return self._transforms(joint_angles)[..., :3, :3]

    forward = rotations
