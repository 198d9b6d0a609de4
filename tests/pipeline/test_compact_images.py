"""A prepared subject keeps 8-bit images as uint8 and gives back the floats the reader made."""

from __future__ import annotations

import numpy as np
import torch

from torchfit.io.images import load_frames, write_image
from torchfit.pipeline.prepare import PreparedSubject, compact_images


def test_eight_bit_images_are_kept_as_bytes_and_read_back_exactly(tmp_path):
    g = np.random.default_rng(0)
    paths = []
    for i in range(2):
        path = tmp_path / f"im{i}.png"
        write_image(path, g.integers(0, 256, size=(9, 11, 3), dtype=np.uint8))
        paths.append(path)
    images, _ = load_frames(paths, size=(11, 9))
    packed = compact_images(images)
    assert packed.dtype == torch.uint8 and packed.shape == images.shape
    prepared = PreparedSubject(None, packed, None, None, 0.0)
    assert torch.equal(prepared.float_images(), images)
    assert torch.equal(prepared.float_images([1]), images[[1]])


def test_images_changed_after_reading_stay_float():
    images = torch.full((1, 3, 4, 5), 10 / 255.0)
    images[0, 0, 0, 0] = 0.5  # not an 8-bit value
    kept = compact_images(images)
    assert kept is images
    assert torch.equal(PreparedSubject(None, kept, None, None, 0.0).float_images(), images)
    assert compact_images(images.double()).dtype == torch.float64
