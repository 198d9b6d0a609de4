"""Pixel scores of segmentation masks against CDnet-style ground truth.

Conventions: masks ``(H, W)`` (also ``(1, H, W)`` or ``(1, 1, H, W)``), non-zero = person, as
NumPy arrays or tensors; labels ``(H, W)`` ``uint8`` in the CDnet coding (255 person, 50
shadow, 85 outside the region of interest, 170 unknown band, 0 background).
"""

from __future__ import annotations

import numpy as np
import torch

from torchfit.errors import ShapeError

__all__ = ["cdnet_counts", "precision_recall_f"]


def cdnet_counts(pred: np.ndarray | torch.Tensor, labels: np.ndarray) -> dict[str, int]:
    """Pixel counts of a predicted mask against a CDnet-style label image.

    Labels: 255 person; 85 (outside the region of interest) and 170 (unknown band) are ignored;
    everything else (0, 50 = shadow, stray low values) is background.

    Args:
        pred: ``(H, W)`` mask (or ``(1, H, W)``, ``(1, 1, H, W)``), non-zero = person.
        labels: ``(H, W)`` uint8 ground truth.

    Returns:
        ``tp, fp, fn, tn`` and ``shadow`` (pixels labelled 50) with ``shadow_as_background``
        (of those, predicted background).
    """
    if isinstance(pred, torch.Tensor):
        pred = pred.detach().cpu().numpy()
    pred = np.asarray(pred)
    while pred.ndim > 2 and pred.shape[0] == 1:  # accept (1, H, W) and (1, 1, H, W)
        pred = pred[0]
    pred = pred != 0
    labels = np.asarray(labels)
    if pred.shape != labels.shape:
        raise ShapeError(f"labels: expected shape {pred.shape} of the mask, got {labels.shape}")
    valid = (labels != 85) & (labels != 170)
    fg = labels == 255
    bg = valid & ~fg
    shadow = labels == 50
    return {
        "tp": int((pred & fg).sum()),
        "fp": int((pred & bg).sum()),
        "fn": int((~pred & fg).sum()),
        "tn": int((~pred & bg).sum()),
        "shadow": int(shadow.sum()),
        "shadow_as_background": int((~pred & shadow).sum()),
    }


def precision_recall_f(counts: dict[str, int]) -> tuple[float, float, float]:
    """Precision, recall and F-measure from summed :func:`cdnet_counts`.

    Args:
        counts: with at least ``tp``, ``fp`` and ``fn`` (scalar pixel counts).

    Returns:
        ``(precision, recall, f)``, each in ``[0, 1]`` and 0 where undefined.
    """
    tp, fp, fn = counts["tp"], counts["fp"], counts["fn"]
    precision = tp / (tp + fp) if tp + fp else 0.0
    recall = tp / (tp + fn) if tp + fn else 0.0
    f = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return precision, recall, f
