"""CDnet pixel counts and precision / recall / F."""

from __future__ import annotations

import numpy as np
import pytest

from torchfit.errors import ShapeError
from torchfit.eval.metrics import cdnet_counts, precision_recall_f


def test_cdnet_counts_convention() -> None:
    labels = np.array([[0, 50, 85, 170, 255, 255, 1]], np.uint8)
    pred = np.array([[1, 0, 1, 1, 1, 0, 0]], bool)
    c = cdnet_counts(pred, labels)
    assert c == {"tp": 1, "fp": 1, "fn": 1, "tn": 2, "shadow": 1, "shadow_as_background": 1}
    assert precision_recall_f(c) == pytest.approx((0.5, 0.5, 0.5))
    assert precision_recall_f({"tp": 0, "fp": 0, "fn": 0}) == (0.0, 0.0, 0.0)
    with pytest.raises(ShapeError, match="labels: expected shape"):
        cdnet_counts(pred, labels[:, :3])
