"""A posed body (:class:`BodyOutput`), what :class:`torchfit.body.model.BodyModel` gives."""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["BodyOutput"]


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
