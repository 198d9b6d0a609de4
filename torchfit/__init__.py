"""torchfit: fit personal 3D body models to silhouettes from one calibrated camera.

Importing ``torchfit`` loads only the light core (errors); the stages live in their
own packages (``torchfit.image``, ``torchfit.body``, ``torchfit.fit``, ``torchfit.pipeline``,
…; see ARCHITECTURE.md) and TensorBoard is imported only by ``torchfit.pipeline.tensorboard``.
"""

from torchfit.errors import (
    CameraError,
    ConfigError,
    DataError,
    ModelError,
    SegmentationError,
    ShapeError,
    TorchfitError,
)

__version__ = "0.1.0"

__all__ = [
    "__version__",
    "TorchfitError",
    "ConfigError",
    "ShapeError",
    "DataError",
    "CameraError",
    "ModelError",
    "SegmentationError",
]
