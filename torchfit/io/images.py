"""Reading and writing images and masks, with errors that name the file.

Files are read into memory in Python and decoded with ``cv2.imdecode``; PNG and JPEG files are
first checked to be complete (every PNG chunk present with a correct checksum, up to ``IEND``;
a JPEG ending with its end-of-image marker), so that a truncated or damaged file gives one
:class:`~torchfit.errors.DataError` naming it, instead of libpng's own message on stderr or a
JPEG silently decoded grey where the data ends. Images and masks are written atomically
(:func:`torchfit.io.files.write_atomic`).

Conventions: colour images are ``(H, W, 3)`` ``uint8`` RGB arrays on disk-side and
``(N, 3, H, W)`` ``float32`` tensors in ``[0, 1]`` on the torch side; masks are ``(H, W)``
``uint8`` arrays (``0`` background, ``255`` person when written by torchfit; ground-truth
label images keep their raw values, e.g. the CDnet labels 0/50/85/170/255).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from torchfit.errors import DataError
from torchfit.io.files import write_atomic

__all__ = [
    "IMAGE_SUFFIXES",
    "list_images",
    "read_image",
    "read_mask",
    "read_silhouette",
    "write_mask",
    "write_image",
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


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _incomplete(data: bytes, suffix: str) -> str | None:
    """Why a PNG or JPEG file's bytes are not a whole file (None when they are, or for other
    formats)."""
    if suffix == ".png" and data.startswith(_PNG_SIGNATURE):
        view, pos = memoryview(data), len(_PNG_SIGNATURE)
        while pos + 8 <= len(data):
            length, kind = struct.unpack(">I4s", view[pos : pos + 8])
            end = pos + 12 + length
            if end > len(data):
                return f"truncated PNG file (the {kind.decode('latin-1')} chunk is cut off)"
            if zlib.crc32(view[pos + 4 : end - 4]) != struct.unpack(">I", view[end - 4 : end])[0]:
                return f"damaged PNG file (bad checksum in a {kind.decode('latin-1')} chunk)"
            if kind == b"IEND":
                return None
            pos = end
        return "truncated PNG file (no IEND chunk)"
    if suffix in (".jpg", ".jpeg") and data.startswith(b"\xff\xd8"):
        if not data.rstrip(b"\0\r\n ").endswith(b"\xff\xd9"):
            return "truncated JPEG file (no end-of-image marker)"
    return None


def _read_uint8(path: Path, what: str) -> np.ndarray:
    """The 8-bit pixels of an image file as OpenCV decodes them; DataError naming ``path``."""
    if not path.is_file():
        raise DataError(f"{what} not found: {path}")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read {what} {path}: {exc.strerror or exc}") from None
    problem = _incomplete(data, path.suffix.lower())
    if problem is not None:
        raise DataError(f"cannot read {what} {path}: {problem}")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
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


def read_mask(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a single-channel 8-bit mask or label image, keeping its raw values.

    Args:
        path: image file (a colour file is accepted when its three channels are equal).
        size: ``(width, height)`` the mask must have (a camera's ``image_size``), or None.

    Returns:
        ``(H, W)`` ``uint8`` array.

    Raises:
        DataError: naming ``path`` if it is missing, unreadable, not 8-bit, truly colour or
        not of ``size``.
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
    if size is not None and img.shape != (size[1], size[0]):
        raise DataError(
            f"{path}: mask is {img.shape[1]}x{img.shape[0]} pixels, camera.yaml image_size is "
            f"{size[0]}x{size[1]}"
        )
    return np.ascontiguousarray(img)


def read_silhouette(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """A user's silhouette mask (``masks/``) as ``(H, W)`` bool: above 127 is the person.

    Raises:
        DataError: as :func:`read_mask`, and for a mask with no pixel above 127 but some above
        0 (stored as 0 and 1, say, where 255 is the person), naming the rule.
    """
    mask = read_mask(path, size)
    top = int(mask.max())
    if 0 < top <= 127:
        raise DataError(
            f"mask {path}: no pixel above 127 (its values are 0..{top}); a mask is 8-bit, "
            "above 127 the person (255 and 0, not 1 and 0)"
        )
    return mask > 127


def write_mask(path: str | Path, mask: np.ndarray | torch.Tensor) -> None:
    """Write a binary mask as an 8-bit PNG with values 0 (background) and 255 (person).

    Args:
        path: output file (its folder is created); the format follows the suffix (use ``.png``).
        mask: ``(H, W)`` or ``(1, H, W)`` array or tensor; non-zero means person.

    Raises:
        DataError: if ``mask`` is not 2-D after squeezing or the suffix is not an image format;
        OutputError: the file cannot be written.
    """
    path = Path(path)
    if isinstance(mask, torch.Tensor):
        mask = mask.detach().cpu().numpy()
    mask = np.asarray(mask)
    if mask.ndim == 3 and mask.shape[0] == 1:
        mask = mask[0]
    if mask.ndim != 2:
        raise DataError(f"write_mask({path}): expected a (H, W) mask, got shape {mask.shape}")
    _write_pixels(path, np.where(mask != 0, 255, 0).astype(np.uint8), "mask")


def _write_pixels(path: Path, pixels: np.ndarray, what: str) -> None:
    try:
        ok, encoded = cv2.imencode(path.suffix, pixels)
    except cv2.error:
        ok = False
    if not ok:
        raise DataError(f"cannot write {what} {path}: unsupported image suffix {path.suffix!r}")
    write_atomic(path, encoded.tobytes())


def write_image(path: str | Path, image: np.ndarray) -> None:
    """Write a colour image atomically; the format follows the suffix (use ``.png``).

    Args:
        path: output file (its folder is created).
        image: ``(H, W, 3)`` ``uint8`` RGB array.

    Raises:
        DataError: a wrong shape or dtype, or an unsupported suffix; OutputError: the file
            cannot be written.
    """
    path = Path(path)
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise DataError(
            f"write_image({path}): expected a (H, W, 3) uint8 image, got {image.dtype} "
            f"{image.shape}"
        )
    _write_pixels(path, np.ascontiguousarray(image[:, :, ::-1]), "image")


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
