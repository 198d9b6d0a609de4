"""The skeleton as a pytorch-kinematics chain (the only importer of pytorch_kinematics).

The chain gives the world rotation of every segment frame for a batch of joint angles. Segment
positions are composed separately (:mod:`torchfit.body.model`) because segment scales change
the joint offsets per subject, which a chain with fixed URDF offsets cannot express; rotations
do not depend on those offsets.

pytorch-kinematics 0.10 writes its transforms in place and does not run under
``torch.func.vmap``; it is called with its plain-autograd path (``analytical_grad=False``) so
that both reverse- and forward-mode AD (``torch.autograd.forward_ad``, tangents folded into the
batch) flow through it.
"""

from __future__ import annotations

import logging
import warnings

import numpy as np
import torch

from torchfit._dual import is_dual, lift
from torchfit.errors import ModelError, check_shape

__all__ = ["SkeletonChain"]

log = logging.getLogger(__name__)


class SkeletonChain:
    """Joint angles (B, Q) -> segment rotations (B, S, 3, 3) and zero-pose offsets.

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
        import pytorch_kinematics as pk

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                self.chain = pk.build_chain_from_urdf(urdf).to(dtype=dtype)
        except Exception as exc:  # the URDF parser raises assorted types
            raise ModelError(f"{source}: pytorch-kinematics cannot load the URDF: {exc}") from exc
        self.dof_names: list[str] = list(self.chain.get_joint_parameter_names())
        frame_names = [self.chain.idx_to_frame[i] for i in range(len(self.chain.idx_to_frame))]
        self._frame_index = {}
        for seg in segments:
            name = seg if seg in frame_names else f"{seg}_frame"
            if name not in frame_names:
                raise ModelError(f"{source}: link {seg!r} missing from the kinematic chain")
            self._frame_index[seg] = frame_names.index(name)
        self.frame_indices = torch.tensor([self._frame_index[s] for s in segments])
        lower, upper = self.chain.get_joint_limits()
        self.lower = torch.as_tensor(np.asarray(lower), dtype=dtype)
        self.upper = torch.as_tensor(np.asarray(upper), dtype=dtype)
        self.parents = np.asarray(parents)
        self.offsets = self._segment_offsets(source, dtype)

    @property
    def num_dofs(self) -> int:
        return len(self.dof_names)

    def _transforms(self, joint_angles: torch.Tensor) -> torch.Tensor:
        # (num_frames, B, 4, 4) -> segment frames (B, S, 4, 4)
        if is_dual(joint_angles):
            # the chain's constants as zero-tangent duals: mixed dual/plain arithmetic is slow
            saved = self.chain.axes, self.chain._static_offsets
            self.chain.axes = lift(saved[0], True)
            self.chain._static_offsets = lift(saved[1], True)
            try:
                all_t = self.chain.forward_kinematics_tensor(joint_angles, analytical_grad=False)
            finally:
                self.chain.axes, self.chain._static_offsets = saved
        else:
            all_t = self.chain.forward_kinematics_tensor(joint_angles, analytical_grad=False)
        return all_t[self.frame_indices].transpose(0, 1)

    def _segment_offsets(self, source: str, dtype: torch.dtype) -> torch.Tensor:
        """(S, 3) origin of each segment in its parent's frame; checks it is pose-independent."""
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

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None):
        """Move the chain and its tensors (returns self)."""
        self.chain = self.chain.to(dtype=dtype, device=device)
        self.lower = self.lower.to(device=device, dtype=dtype)
        self.upper = self.upper.to(device=device, dtype=dtype)
        self.offsets = self.offsets.to(device=device, dtype=dtype)
        self.frame_indices = self.frame_indices.to(device=device)
        return self
