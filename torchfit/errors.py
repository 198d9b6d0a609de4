"""Typed exceptions and the one shape-check helper.

Every error raised for bad input from a caller subclasses :class:`TorchfitError` (itself a
``ValueError``) and names the argument, what was expected and what was found.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = [
    "TorchfitError",
    "ConfigError",
    "ShapeError",
    "DataError",
    "CameraError",
    "ModelError",
    "SegmentationError",
    "SequenceError",
    "OutputError",
    "check_shape",
    "yaml_problem",
]


class TorchfitError(ValueError):
    """Base class of all torchfit input errors."""


class ConfigError(TorchfitError):
    """A configuration file or override is invalid (unknown key, wrong type, bad YAML)."""


class ShapeError(TorchfitError):
    """A tensor argument has the wrong shape or dtype."""


class DataError(TorchfitError):
    """A dataset file is missing, unreadable or inconsistent."""


class CameraError(TorchfitError):
    """A camera description is invalid."""


class ModelError(TorchfitError):
    """A body model (URDF, meshes, parameter vector) is invalid."""


class SegmentationError(TorchfitError):
    """Segmentation failed for an image (no person found, size mismatch, …)."""


class SequenceError(DataError):
    """One of the sequences tracked together cannot be read or segmented (a frame or mask
    unreadable or of another size, too few background frames, ...): ``index`` is its position
    among them, the message is the error's. The others are not at fault."""

    def __init__(self, index: int, message: str) -> None:
        super().__init__(message)
        self.index = index

    def __reduce__(self):  # pickled as it was made (a reader process raises it)
        return type(self), (self.index, str(self))


class OutputError(TorchfitError):
    """A run's outputs cannot be written: a read-only or full disk, missing permissions, a
    folder that vanished or a path through a regular file. The message names the path and the
    system's reason. Not the caller's input, but raised the same way so that a tool reports it
    in one line (``tools/fit.py`` exits with code 3)."""


def check_shape(name: str, tensor: torch.Tensor, shape: Sequence[int | str | None]) -> None:
    """Check ``tensor.shape`` against a pattern.

    Args:
        name: argument name used in the error message.
        tensor: the tensor to check.
        shape: expected shape; an ``int`` must match exactly, a ``str`` or ``None`` matches any
            size (strings are symbolic names used in the message, e.g. ``("B", "N", 3)``).

    Raises:
        ShapeError: naming ``name``, the expected pattern and the actual shape.
    """
    if not isinstance(tensor, torch.Tensor):
        raise ShapeError(f"{name}: expected a torch.Tensor, got {type(tensor).__name__}")
    pattern = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
    if tensor.dim() != len(shape) or any(
        isinstance(s, int) and tensor.shape[i] != s for i, s in enumerate(shape)
    ):
        raise ShapeError(f"{name}: expected shape {pattern}, got {tuple(tensor.shape)}")


def yaml_problem(exc: Exception) -> str:
    """A YAML parser's error in one line: what is wrong and where (``line L, column C``)."""
    problem = getattr(exc, "problem", None)
    mark = getattr(exc, "problem_mark", None)
    if problem is None:
        return " ".join(str(exc).split())
    context = getattr(exc, "context", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"{problem}{where}" + (f" ({context})" if context else "")
