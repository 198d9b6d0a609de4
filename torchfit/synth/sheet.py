"""Contact sheets: the six posture images of a few subjects on one page, for eyeballing."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from torchfit.errors import DataError
from torchfit.synth.postures import POSTURES
from torchfit.viz.raster import draw_label

__all__ = ["contact_sheet"]


def contact_sheet(
    folders: Sequence[str | Path],
    path: str | Path,
    thumb_width: int = 200,
    stereo: bool = True,
    levels: int = 64,
) -> np.ndarray:
    """Write a PNG with one row per subject: pose1 … pose6 (and the stereo left image).

    Args:
        folders: subject folders (design.md section 3 layout).
        path: the PNG to write.
        thumb_width: width of each thumbnail in pixels.
        stereo: add the stereo left image where the subject has one.
        levels: grey levels kept per channel (fewer make a smaller PNG; 256 keeps all).

    Returns:
        (H, W, 3) uint8 BGR sheet.

    Raises:
        DataError: a posture image is missing or unreadable.
    """
    rows = []
    for folder in folders:
        folder = Path(folder)
        files = [folder / "poses" / f"pose{p.index}.png" for p in POSTURES]
        labels = [f"{p.index} {p.name}" for p in POSTURES]
        if stereo and (folder / "stereo" / "left.png").is_file():
            files.append(folder / "stereo" / "left.png")
            labels.append("stereo left")
        thumbs = []
        for file, label in zip(files, labels, strict=True):
            img = cv2.imread(str(file))
            if img is None:
                raise DataError(f"{file}: missing or unreadable posture image")
            h = round(img.shape[0] * thumb_width / img.shape[1])
            img = cv2.resize(img, (thumb_width, h), interpolation=cv2.INTER_AREA)
            text = f"{folder.name}: {label}"
            draw_label(img, text, (5, 16), 0.42)
            thumbs.append(img)
        while len(thumbs) < len(POSTURES) + int(stereo):
            thumbs.append(np.zeros_like(thumbs[0]))
        rows.append(np.hstack(thumbs))
    sheet = np.vstack(rows)
    step = 256 // max(1, min(levels, 256))
    if step > 1:
        sheet = (sheet // step * step + step // 2).astype(np.uint8)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), sheet, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return sheet
