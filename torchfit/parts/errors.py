"""The typed error of :mod:`torchfit.parts`."""

from __future__ import annotations

from torchfit.errors import TorchfitError

__all__ = ["PartsError"]


class PartsError(TorchfitError):
    """Bad input to the silhouette part decomposition (wrong shape, option out of range)."""
