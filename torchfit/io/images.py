"""Reading and writing images and masks, with errors that name the file.

Conventions: colour images are ``(H, W, 3)`` ``uint8`` RGB arrays on disk-side and
``(N, 3, H, W)`` ``float32`` tensors in ``[0, 1]`` on the torch side; masks are ``(H, W)``
``uint8`` arrays (``0`` background, ``255`` person when written by torchfit; ground-truth
label images keep their raw values, e.g. the CDnet labels 0/50/85/170/255).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from torchfit.errors import DataError

__all__ = [
    "IMAGE_SUFFIXES",
    "list_images",
    "read_image",
    "read_mask",
    "write_mask",
    "load_frames",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def list_images(folder: str | Path) -> list[Path]:
    """The image files of a folder (suffixes in :data:`IMAGE_SUFFIXES`), sorted by name.

    Raises:
        DataError: if ``folder`` is not a directory.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"image folder not found: {folder} (expected a directory)")
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _read_uint8(path: Path, what: str) -> np.ndarray:
    """The 8-bit pixels of an image file as OpenCV reads them; DataError naming ``path``."""
    if not path.is_file():
        raise DataError(f"{what} not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"cannot read {what} {path}: not a readable image file")
    if img.dtype != np.uint8:
        raise DataError(f"{what} {path}: expected 8-bit pixels, got dtype {img.dtype}")
    return img


def read_image(path: str | Path) -> np.ndarray:
    """Read a colour image as RGB.

    Grey images are replicated to three channels; an alpha channel is dropped; 16-bit images
    are rejected (torchfit works on 8-bit frames).

    Args:
        path: image file.

    Returns:
        ``(H, W, 3)`` ``uint8`` RGB array.

    Raises:
        DataError: naming ``path`` if it is missing, unreadable or not an 8-bit image.
    """
    path = Path(path)
    img = _read_uint8(path, "image")
    if img.ndim == 2:
        return np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))
    if img.ndim == 3 and img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    if img.ndim == 3 and img.shape[2] == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    raise DataError(f"image {path}: expected 1, 3 or 4 channels, got shape {img.shape}")


def read_mask(path: str | Path) -> np.ndarray:
    """Read a single-channel 8-bit mask or label image, keeping its raw values.

    Args:
        path: image file (a colour file is accepted when its three channels are equal).

    Returns:
        ``(H, W)`` ``uint8`` array.

    Raises:
        DataError: naming ``path`` if it is missing, unreadable, not 8-bit or truly colour.
    """
    path = Path(path)
    img = _read_uint8(path, "mask")
    if img.ndim == 3:
        chan = img[:, :, :3]
        if not (
            np.array_equal(chan[:, :, 0], chan[:, :, 1])
            and np.array_equal(chan[:, :, 0], chan[:, :, 2])
        ):
            raise DataError(f"mask {path}: expected a single-channel image, got colour {img.shape}")
        img = chan[:, :, 0]
    return np.ascontiguousarray(img)


def write_mask(path: str | Path, mask: np.ndarray | torch.Tensor) -> None:
    """Write a binary mask as an 8-bit PNG with values 0 (background) and 255 (person).

    Args:
        path: output file (its folder is created); the format follows the suffix (use ``.png``).
        mask: ``(H, W)`` or ``(1, H, W)`` array or tensor; non-zero means person.

    Raises:
        DataError: if ``mask`` is not 2-D after squeezing, or writing fails.
    """
    path = Path(path)
    if isinstance(mask, torch.Tensor):
        mask = mask.detach().cpu().numpy()
    mask = np.asarray(mask)
    if mask.ndim == 3 and mask.shape[0] == 1:
        mask = mask[0]
    if mask.ndim != 2:
        raise DataError(f"write_mask({path}): expected a (H, W) mask, got shape {mask.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), np.where(mask != 0, 255, 0).astype(np.uint8)):
        raise DataError(f"cannot write mask {path} (unsupported suffix or unwritable folder)")


def load_frames(
    source: str | Path | Sequence[str | Path],
    size: tuple[int, int] | None = None,
) -> tuple[torch.Tensor, list[Path]]:
    """Load a folder (or a list) of colour frames that must all have one size.

    Args:
        source: a folder (its images sorted by name) or a sequence of image files.
        size: expected ``(width, height)``; ``None`` takes the size of the first frame.

    Returns:
        ``frames``: ``(N, 3, H, W)`` ``float32`` RGB in ``[0, 1]``, and the ``N`` paths read.

    Raises:
        DataError: for an empty folder, an unreadable file, or a frame whose size differs
            (the message names the file, the expected and the actual size).
    """
    paths = list_images(source) if isinstance(source, (str, Path)) else [Path(p) for p in source]
    if not paths:
        raise DataError(f"no images ({', '.join(IMAGE_SUFFIXES)}) found in {source}")
    arrays = []
    for p in paths:
        img = read_image(p)
        h, w = img.shape[:2]
        if size is None:
            size = (w, h)
        if (w, h) != tuple(size):
            raise DataError(f"frame {p}: expected size {size[0]}x{size[1]} (WxH), got {w}x{h}")
        arrays.append(img)
    stack = torch.from_numpy(np.stack(arrays)).permute(0, 3, 1, 2)
    return stack.float().div_(255.0).contiguous(), paths
