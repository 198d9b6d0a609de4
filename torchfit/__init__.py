"""torchfit: fit personal 3D body models to silhouettes from one calibrated camera.

Importing ``torchfit`` loads only the light core (errors, config); the stages live in their
own modules (``torchfit.camera``, ``torchfit.body``, ``torchfit.image``, …) and
TensorBoard is imported only by ``torchfit.tb_logging``.
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
