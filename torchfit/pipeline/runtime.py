"""Process-wide runtime settings of a run: torch threads, the allocator, dtype and device."""

from __future__ import annotations

import logging

import torch

from torchfit.config.schema import RunConfig
from torchfit.solver import keep_heap

__all__ = ["apply_runtime", "torch_dtype"]

log = logging.getLogger(__name__)


def torch_dtype(name: str) -> torch.dtype:
    """``"float32"`` / ``"float64"`` as a torch dtype."""
    return torch.float64 if name == "float64" else torch.float32


def apply_runtime(run: RunConfig) -> None:
    """Set the torch thread count and glibc's heap policy as ``run`` asks."""
    if run.num_threads:
        torch.set_num_threads(run.num_threads)
    if run.keep_heap and not keep_heap():
        log.warning("run.keep_heap: the C library is not glibc; the setting has no effect")
