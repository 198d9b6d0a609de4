"""Image and mask I/O: channel order, value ranges and errors that name the file."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchfit.errors import DataError
from torchfit.io import list_images, load_frames, read_image, read_mask, write_mask


def test_read_image_is_rgb_and_handles_grey_and_alpha(tmp_path: Path) -> None:
    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[..., 0] = 10  # blue
    bgr[..., 2] = 200  # red
    cv2.imwrite(str(tmp_path / "c.png"), bgr)
    rgb = read_image(tmp_path / "c.png")
    assert rgb.shape == (4, 5, 3) and rgb.dtype == np.uint8
    assert rgb[0, 0].tolist() == [200, 0, 10]
    cv2.imwrite(str(tmp_path / "g.png"), np.full((4, 5), 77, np.uint8))
    assert read_image(tmp_path / "g.png")[1, 2].tolist() == [77, 77, 77]
    bgra = np.dstack([bgr, np.full((4, 5), 255, np.uint8)])
    cv2.imwrite(str(tmp_path / "a.png"), bgra)
    assert read_image(tmp_path / "a.png")[0, 0].tolist() == [200, 0, 10]


def test_read_errors_name_the_file(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="image not found: .*missing.png"):
        read_image(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"garbage")
    with pytest.raises(DataError, match="cannot read image .*bad.png"):
        read_image(tmp_path / "bad.png")
    with pytest.raises(DataError, match="cannot read mask .*bad.png"):
        read_mask(tmp_path / "bad.png")
    cv2.imwrite(str(tmp_path / "deep.png"), np.zeros((3, 3), np.uint16))
    with pytest.raises(DataError, match="deep.png: expected 8-bit pixels, got dtype uint16"):
        read_image(tmp_path / "deep.png")
    cv2.imwrite(
        str(tmp_path / "colour.png"),
        np.dstack([np.zeros((3, 3)), np.ones((3, 3)), np.zeros((3, 3))]).astype(np.uint8),
    )
    with pytest.raises(DataError, match="colour.png: expected a single-channel image"):
        read_mask(tmp_path / "colour.png")
    with pytest.raises(DataError, match="image folder not found"):
        list_images(tmp_path / "nope")


def test_mask_round_trip(tmp_path: Path) -> None:
    labels = np.array([[0, 50, 170], [255, 85, 1]], np.uint8)
    cv2.imwrite(str(tmp_path / "gt.png"), labels)
    np.testing.assert_array_equal(read_mask(tmp_path / "gt.png"), labels)  # raw values kept
    mask = torch.tensor([[[True, False, True], [False, False, True]]])
    write_mask(tmp_path / "sub" / "m.png", mask)
    back = read_mask(tmp_path / "sub" / "m.png")
    np.testing.assert_array_equal(back, np.array([[255, 0, 255], [0, 0, 255]], np.uint8))
    with pytest.raises(DataError, match=r"expected a \(H, W\) mask"):
        write_mask(tmp_path / "x.png", np.zeros((2, 2, 2)))


def test_load_frames_checks_sizes(tmp_path: Path) -> None:
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.full((6, 8, 3), 40 * i, np.uint8))
    (tmp_path / "notes.txt").write_text("ignored")
    frames, paths = load_frames(tmp_path)
    assert frames.shape == (3, 3, 6, 8) and frames.dtype == torch.float32
    assert [p.name for p in paths] == ["f0.png", "f1.png", "f2.png"]
    assert frames[2].max().item() == pytest.approx(80 / 255)
    cv2.imwrite(str(tmp_path / "f3.png"), np.zeros((7, 8, 3), np.uint8))
    with pytest.raises(DataError, match=r"frame .*f3.png: expected size 8x6 \(WxH\), got 8x7"):
        load_frames(tmp_path)
    with pytest.raises(DataError, match="expected size 9x6"):
        load_frames([tmp_path / "f0.png"], size=(9, 6))
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no images"):
        load_frames(tmp_path / "empty")
