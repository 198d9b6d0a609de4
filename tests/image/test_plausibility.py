"""Plausibility of a silhouette: hand-built masks with known area, box and border contacts, and
the silhouettes of the demo subjects' six postures (all plausible)."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchfit.errors import ShapeError
from torchfit.image import PlausibilityOptions, implausible, silhouette_shape

H, W = 576, 720
REPO = Path(__file__).resolve().parents[2]


def _mask(draw) -> torch.Tensor:
    m = np.zeros((H, W), np.uint8)
    draw(m)
    return torch.from_numpy(m.astype(bool))[None, None]


def _standing(m: np.ndarray) -> None:
    cv2.ellipse(m, (360, 300), (45, 170), 0, 0, 360, 1, -1)
    cv2.circle(m, (360, 110), 25, 1, -1)


def _t_pose(m: np.ndarray) -> None:
    _standing(m)
    cv2.rectangle(m, (190, 170), (530, 185), 1, -1)


def test_shape_of_a_rectangle_matches_hand_counts() -> None:
    m = torch.zeros(2, 1, 10, 20, dtype=torch.bool)
    m[0, 0, 2:8, 0:5] = True  # 6 x 5, touches the left border
    m[0, 0, 5, 10] = True  # a second region widens the box to 6 x 11
    shape = silhouette_shape(m)
    torch.testing.assert_close(shape["area"], torch.tensor([31 / 200, 0.0], dtype=torch.float64))
    torch.testing.assert_close(shape["aspect"], torch.tensor([6 / 11, 0.0], dtype=torch.float64))
    torch.testing.assert_close(shape["fill"], torch.tensor([31 / 66, 0.0], dtype=torch.float64))
    assert shape["touches"].tolist() == [[False, False, True, False], [False] * 4]
    assert shape["borders"].tolist() == [1, 0]


def test_bodies_in_the_postures_are_plausible() -> None:
    masks = torch.cat([_mask(_standing), _mask(_t_pose)])
    assert implausible(masks) == [None, None]


@pytest.mark.parametrize(
    ("draw", "pattern"),
    [
        (lambda m: m.fill(1), r"covers 100 % of the image \(at most 50 %\).*touches 4 image"),
        (
            lambda m: cv2.rectangle(m, (0, 100), (719, 575), 1, -1),
            r"touches 3 image borders \(bottom, left, right; at most 2\)",
        ),
        (lambda m: cv2.circle(m, (300, 300), 8, 1, -1), r"covers 0.0\d+ % of the image"),
        (lambda m: cv2.rectangle(m, (100, 300), (600, 360), 1, -1), r"0.12 times as high as wide"),
        (lambda m: cv2.rectangle(m, (300, 100), (420, 400), 1, -1), r"fills 100 % of its bounding"),
    ],
)
def test_what_cannot_be_a_person_is_named(draw, pattern) -> None:
    (why,) = implausible(_mask(draw))
    assert why is not None
    assert re.search(pattern, why), why


def test_empty_masks_and_switching_off() -> None:
    masks = torch.zeros(2, 1, H, W, dtype=torch.bool)
    masks[1] = True
    off = PlausibilityOptions(enabled=False)
    assert implausible(masks, off) == ["the silhouette is empty", None]
    assert implausible(masks)[0] == "the silhouette is empty"


def test_errors_name_the_argument() -> None:
    with pytest.raises(ShapeError, match="masks: expected shape"):
        implausible(torch.zeros(H, W, dtype=torch.bool))
    with pytest.raises(ShapeError, match="masks: expected a bool tensor"):
        implausible(torch.zeros(1, 1, H, W))
    with pytest.raises(ValueError, match="options.fill must satisfy"):
        implausible(_mask(_standing), PlausibilityOptions(fill=(0.9, 0.1)))


def test_demo_postures_are_plausible() -> None:
    """The six postures of both demo subjects, segmented with the demo config: their shapes
    lie inside the bounds (T-pose fill about 0.2, side view aspect about 5.5)."""
    from torchfit.config import load_config
    from torchfit.io.dataset import load_dataset
    from torchfit.pipeline import segment_subject

    config = load_config(REPO / "configs" / "demo.yaml")
    for subject in load_dataset(REPO / "data" / "demo"):
        _, masks, _ = segment_subject(subject, config)
        assert implausible(masks[:, None]) == [None] * 6, subject.name
