"""Chroma key (torchfit.image.chroma) on small synthetic frames."""

from __future__ import annotations

import pytest
import torch

from torchfit.errors import ConfigError, SegmentationError
from torchfit.image.chroma import (
    ChromaKeyOptions,
    chroma_key,
    despill,
    estimate_key,
    screen_frame,
)

GREEN = torch.tensor([0.2, 0.7, 0.25])


def _scene(h: int = 40, w: int = 60, seed: int = 0):
    """Background frames of a green screen (a grey studio strip on the left), and a frame with
    a person block (skin, dark shirt), a half-covered edge column and a shadow on the screen."""
    g = torch.Generator().manual_seed(seed)
    screen = GREEN.view(3, 1, 1).expand(3, h, w).clone()
    screen[:, :, :6] = 0.5  # studio wall beside the screen
    background = (screen + 0.01 * torch.randn(5, 3, h, w, generator=g)).clamp(0, 1)
    frame = screen.clone()
    frame[:, 10:30, 20:30] = torch.tensor([0.8, 0.6, 0.5]).view(3, 1, 1)  # skin
    frame[:, 10:30, 30:35] = torch.tensor([0.1, 0.1, 0.12]).view(3, 1, 1)  # dark shirt
    frame[:, 10:30, 35] = 0.7 * frame[:, 10:30, 34] + 0.3 * screen[:, 10:30, 35]  # 70 % person
    frame[:, 10:30, 36] = 0.3 * frame[:, 10:30, 34] + 0.7 * screen[:, 10:30, 36]  # 30 % person
    frame[:, 32:38, 20:50] *= 0.55  # the person's shadow on the screen
    frame[:, 2:6, 1:4] = torch.tensor([0.9, 0.1, 0.1]).view(3, 1, 1)  # an object off-screen
    truth = torch.zeros(h, w, dtype=torch.bool)
    truth[10:30, 20:36] = True
    truth[2:6, 1:4] = True
    frame = (frame + 0.01 * torch.randn(3, h, w, generator=g)).clamp(0, 1)
    return background, frame[None], truth


def test_key_estimated_from_the_background_frames():
    background, _, _ = _scene()
    key = estimate_key(background)
    assert torch.allclose(key, GREEN, atol=0.02)
    with pytest.raises(SegmentationError, match="no coloured screen"):
        estimate_key(torch.full((5, 3, 8, 8), 0.5))


def test_person_edge_shadow_and_off_screen_pixels():
    background, frame, truth = _scene()
    mask = chroma_key(frame, ChromaKeyOptions(), background)[0, 0]
    assert torch.equal(mask, truth)
    # a given key colour without background frames: the studio strip is not screen then
    given = ChromaKeyOptions(key=tuple(float(v) * 255 for v in GREEN))
    mask = chroma_key(frame, given)[0, 0]
    assert torch.equal(mask[:, 6:], truth[:, 6:])


@pytest.mark.parametrize("gamma", [1.0, 2.2])
def test_the_empty_screen_as_one_frame_keys_as_its_frames_do(gamma):
    """A sequence keys every frame against ``screen_frame`` of its background frames, made once:
    the same silhouettes as keying against the frames themselves."""
    background, frame, truth = _scene()
    options = ChromaKeyOptions(gamma=gamma)
    screen = screen_frame(background, options)
    assert screen.shape == (1, *background.shape[1:])
    mask = chroma_key(frame, options, screen)[0, 0]
    assert torch.equal(mask, chroma_key(frame, options, background)[0, 0])
    if gamma == 1.0:  # the scene's person and shadow are keyed right in encoded values
        assert torch.equal(mask, truth)


def test_options_are_checked():
    _, frame, _ = _scene()
    with pytest.raises(ConfigError, match="chroma_key.key is not set"):
        chroma_key(frame, ChromaKeyOptions())
    with pytest.raises(ConfigError, match="chroma_key.tolerance"):
        chroma_key(frame, ChromaKeyOptions(key=(0, 200, 0), tolerance=1.5))
    with pytest.raises(ConfigError, match=r"chroma_key.key: expected \[r, g, b\]"):
        chroma_key(frame, ChromaKeyOptions(key=(0, 300, 0)))


def test_despill_limits_the_key_channel_on_the_edge_only():
    image = torch.zeros(1, 3, 20, 20)
    image[:, :] = torch.tensor([0.5, 0.6, 0.4]).view(1, 3, 1, 1)  # a green tint everywhere
    mask = torch.zeros(1, 1, 20, 20, dtype=torch.bool)
    mask[:, :, 4:16, 4:16] = True
    out = despill(image, mask, GREEN, spill_px=2)
    assert torch.allclose(out[0, 1, 4, 4:16], torch.tensor(0.5))  # edge: green limited
    assert torch.allclose(out[0, 1, 8, 8], torch.tensor(0.6))  # interior unchanged
    assert torch.allclose(out[0, 1, 0, 0], torch.tensor(0.6))  # outside unchanged
    assert torch.equal(out[:, [0, 2]], image[:, [0, 2]])
