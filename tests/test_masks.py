"""A subject's own silhouettes (``masks/``) and ``segmentation.method``."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchfit.config import Config, config_from_dict
from torchfit.errors import ConfigError, DataError
from torchfit.io.dataset import load_dataset, load_subject
from torchfit.io.images import write_mask
from torchfit.pipeline.fingerprint import inputs_digest
from torchfit.pipeline.prepare import segment_subject

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "data" / "demo" / "subject_000"


@pytest.fixture(scope="module")
def demo_masks() -> torch.Tensor:
    """The demo subject's silhouettes from background subtraction (6, H, W) bool."""
    _, masks, _ = segment_subject(load_subject(DEMO), Config().segmentation)
    return masks


def _with_masks(tmp_path: Path, masks: torch.Tensor, background: bool = False) -> Path:
    folder = tmp_path / "s"
    shutil.copytree(DEMO, folder, ignore=None if background else shutil.ignore_patterns("bg*"))
    if not background:
        shutil.rmtree(folder / "background")
    for k, mask in enumerate(masks, start=1):
        write_mask(folder / "masks" / f"pose{k}.png", mask)
    return folder


def test_masks_replace_the_background_frames(tmp_path, demo_masks):
    # the demo subject's silhouettes as masks/, but every other pixel value of a mask not 0 or
    # 255: > 127 is the person
    folder = _with_masks(tmp_path, demo_masks)
    mask1 = np.where(demo_masks[0].numpy(), 200, 100).astype(np.uint8)

    cv2.imwrite(str(folder / "masks" / "pose1.png"), mask1)
    subject = load_subject(folder)
    assert subject.ok, subject.problems
    assert subject.method == "masks" and subject.background == []
    assert [p.name for p in subject.masks] == [f"pose{k}.png" for k in range(1, 7)]
    images, masks, shadow = segment_subject(subject, Config().segmentation)
    assert images.shape[0] == 6
    assert torch.equal(masks, demo_masks)
    assert not shadow.any()


def test_method_background_still_needs_the_frames(tmp_path, demo_masks):
    folder = _with_masks(tmp_path, demo_masks)
    (subject,) = load_dataset(tmp_path, method="background")
    assert not subject.ok
    assert any("background" in p and "expected >= 5" in p for p in subject.problems)
    # auto with both: the masks win; background uses the frames
    folder = _with_masks(tmp_path / "both", demo_masks, background=True)
    assert load_subject(folder).method == "masks"
    assert load_subject(folder, "background").method == "background"
    assert load_subject(folder, "background").masks is None


def test_method_masks_without_masks_names_the_missing_files(tmp_path):
    shutil.copytree(DEMO, tmp_path / "s")
    subject = load_subject(tmp_path / "s", "masks")
    assert not subject.ok
    assert sum("missing mask" in p for p in subject.problems) == 6
    assert load_subject(tmp_path / "s").method == "background"  # auto without masks/


def test_mask_of_the_wrong_size_is_named(tmp_path, demo_masks):
    folder = _with_masks(tmp_path, demo_masks)
    write_mask(folder / "masks" / "pose3.png", np.zeros((10, 12), np.uint8))
    (folder / "masks" / "pose5.png").unlink()
    subject = load_subject(folder)
    text = "; ".join(subject.problems)
    assert "masks/pose3.png: mask is 12x10 pixels, camera.yaml image_size is 720x576" in text
    assert "masks/pose5.png: missing mask" in text
    with pytest.raises(DataError, match="pose3.png"):
        segment_subject(subject, Config().segmentation)


def test_a_mask_of_ones_and_zeros_is_named_with_the_rule(tmp_path, demo_masks):
    """A mask stored as 0 and 1 (no pixel above 127) is named, with what a mask must be,
    instead of "no person found"."""
    folder = _with_masks(tmp_path, demo_masks)
    cv2.imwrite(str(folder / "masks" / "pose3.png"), demo_masks[2].numpy().astype(np.uint8))
    with pytest.raises(DataError, match=r"pose3.png: no pixel above 127 \(its values are 0..1\)"):
        segment_subject(load_subject(folder), Config().segmentation)


def test_masks_enter_the_inputs_digest(tmp_path, demo_masks):
    folder = _with_masks(tmp_path, demo_masks)
    before = inputs_digest(load_subject(folder))
    write_mask(folder / "masks" / "pose2.png", demo_masks[2])
    assert inputs_digest(load_subject(folder)) != before


def test_method_is_checked_by_the_config_and_the_loader(tmp_path):
    assert config_from_dict({"segmentation": {"method": "masks"}}).segmentation.method == "masks"
    with pytest.raises(ConfigError, match="segmentation.method"):
        config_from_dict({"segmentation": {"method": "neural"}})
    with pytest.raises(DataError, match="segmentation method"):
        load_subject(tmp_path, "neural")
