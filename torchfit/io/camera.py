"""``camera.yaml`` files (design.md section 2): one camera, or a stereo pair, to and from
:class:`torchfit.camera.Camera`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
import yaml

from torchfit.camera import ROTATION_TOLERANCE, Camera
from torchfit.errors import CameraError, yaml_problem
from torchfit.io.files import write_atomic

__all__ = [
    "load_camera",
    "save_camera",
    "camera_from_dict",
    "camera_to_dict",
    "load_stereo_cameras",
    "save_stereo_cameras",
]


# --------------------------------------------------------------------------------------------
# camera.yaml


def _matrix(data: dict, key: str, rows: int, cols: int | None, source: str) -> torch.Tensor:
    if key not in data:
        raise CameraError(f"{source}: missing key '{key}'")
    value = data[key]
    shape = f"{rows}x{cols}" if cols else f"{rows}"
    try:
        tensor = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError) as exc:
        raise CameraError(
            f"{source}: key '{key}' expects a {shape} list of numbers, got {value!r}"
        ) from exc
    expected = (rows, cols) if cols else (rows,)
    if tuple(tensor.shape) != expected or isinstance(value, bool):
        raise CameraError(
            f"{source}: key '{key}' expects a {shape} list of numbers, got shape "
            f"{tuple(tensor.shape)}"
        )
    if not bool(torch.isfinite(tensor).all()):
        raise CameraError(f"{source}: key '{key}' contains non-finite values: {value!r}")
    return tensor


def camera_from_dict(data: Any, source: str = "<dict>") -> Camera:
    """Build and validate a single camera (B = 1, float64) from a ``camera.yaml`` mapping.

    Checks: ``image_size`` two positive integers; ``K`` upper triangular with positive focal
    lengths and ``K[2, 2] = 1``; ``dist`` five numbers; ``R`` orthonormal with determinant +1
    (within :data:`ROTATION_TOLERANCE`); ``t`` three numbers.

    Args:
        data: mapping with keys ``image_size, K, dist, R, t``.
        source: name used in error messages (the file path).

    Raises:
        CameraError: naming ``source`` and the offending key.
    """
    if not isinstance(data, dict):
        raise CameraError(f"{source}: expected a mapping of camera keys, got {type(data).__name__}")
    known = {"image_size", "K", "dist", "R", "t"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise CameraError(
            f"{source}: unknown key '{unknown[0]}' (valid keys: {', '.join(sorted(known))})"
        )
    if "image_size" not in data:
        raise CameraError(f"{source}: missing key 'image_size'")
    size = data["image_size"]
    if (
        not isinstance(size, (list, tuple))
        or len(size) != 2
        or any(isinstance(s, bool) or not isinstance(s, int) or s <= 0 for s in size)
    ):
        raise CameraError(
            f"{source}: key 'image_size' expects [width, height] as two positive integers, "
            f"got {size!r}"
        )
    K = _matrix(data, "K", 3, 3, source)
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise CameraError(
            f"{source}: key 'K' must be upper triangular with K[2][2] = 1, got {K.tolist()}"
        )
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CameraError(
            f"{source}: key 'K' must have positive focal lengths, got fx={K[0, 0].item()}, "
            f"fy={K[1, 1].item()}"
        )
    dist = _matrix(data, "dist", 5, None, source)
    R = _matrix(data, "R", 3, 3, source)
    ortho = (R.T @ R - torch.eye(3, dtype=R.dtype)).abs().max().item()
    det = torch.linalg.det(R).item()
    if ortho > ROTATION_TOLERANCE or abs(det - 1) > ROTATION_TOLERANCE:
        raise CameraError(
            f"{source}: key 'R' must be a rotation (orthonormal, det +1, tolerance "
            f"{ROTATION_TOLERANCE}), got max|RᵀR - I| = {ortho:.3g}, det = {det:.6g}"
        )
    t = _matrix(data, "t", 3, None, source)
    return Camera(K=K, dist=dist, R=R, t=t, image_size=(int(size[0]), int(size[1])))


def camera_to_dict(camera: Camera, index: int = 0) -> dict:
    """The ``camera.yaml`` mapping of camera ``index`` of the batch (plain Python floats)."""
    if not -camera.batch_size <= index < camera.batch_size:
        raise CameraError(f"index: expected 0 <= index < {camera.batch_size}, got {index}")

    def plain(x: torch.Tensor) -> list:
        return [float(v) if not isinstance(v, list) else v for v in x.tolist()]

    return {
        "image_size": [int(camera.image_size[0]), int(camera.image_size[1])],
        "K": [plain(row) for row in camera.K[index].detach().double().cpu()],
        "dist": plain(camera.dist[index].detach().double().cpu()),
        "R": [plain(row) for row in camera.R[index].detach().double().cpu()],
        "t": plain(camera.t[index].detach().double().cpu()),
    }


def _read_yaml(path: Path) -> Any:
    if not path.is_file():
        raise CameraError(f"camera file not found: {path}")
    try:
        return yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise CameraError(f"cannot read {path}: {exc}") from None
    except yaml.YAMLError as exc:
        raise CameraError(f"{path}: invalid YAML: {yaml_problem(exc)}") from exc


def _dump(data: dict) -> str:
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=200)


def load_camera(path: str | Path) -> Camera:
    """Read and validate a ``camera.yaml`` file (design.md section 3).

    Returns:
        A :class:`Camera` with B = 1, float64 tensors.

    Raises:
        CameraError: a missing or invalid file; the message names the file and the key.
    """
    path = Path(path)
    return camera_from_dict(_read_yaml(path), str(path))


def save_camera(camera: Camera, path: str | Path, index: int = 0) -> None:
    """Write camera ``index`` of the batch as ``camera.yaml`` (full float precision)."""
    write_atomic(path, _dump(camera_to_dict(camera, index)))


def load_stereo_cameras(path: str | Path) -> tuple[Camera, Camera]:
    """Read a stereo ``cameras.yaml`` (``{left: <camera>, right: <camera>}``).

    Raises:
        CameraError: naming the file and the key (``left.R``, …).
    """
    path = Path(path)
    data = _read_yaml(path)
    if not isinstance(data, dict) or set(data) != {"left", "right"}:
        keys = sorted(data) if isinstance(data, dict) else type(data).__name__
        raise CameraError(f"{path}: expected exactly the keys 'left' and 'right', got {keys}")
    return (
        camera_from_dict(data["left"], f"{path} [left]"),
        camera_from_dict(data["right"], f"{path} [right]"),
    )


def save_stereo_cameras(left: Camera, right: Camera, path: str | Path) -> None:
    """Write a stereo ``cameras.yaml`` from two single cameras."""
    write_atomic(path, _dump({"left": camera_to_dict(left), "right": camera_to_dict(right)}))
