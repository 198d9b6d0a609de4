"""Chroma key on a synthetic green-screen subject, through the pipeline's segmentation."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torchfit.config import Config
from torchfit.io import read_mask
from torchfit.io.dataset import load_subject
from torchfit.pipeline.prepare import segment_subject


@pytest.mark.slow
def test_green_screen_subject_keys_close_to_the_truth(tmp_path):
    pytest.importorskip("anny")
    from torchfit.synth.generate import make_subject
    from torchfit.synth.options import SynthConfig

    cfg = SynthConfig(stereo=False, green_screen=True, spill=0.35, image_size=[480, 384])
    make_subject(tmp_path / "s", 6100, 0, cfg)
    segmentation = dataclasses.replace(Config().segmentation, method="chroma_key")
    subject = load_subject(tmp_path / "s", "chroma_key")
    assert subject.ok, subject.problems
    images, masks, shadow = segment_subject(subject, segmentation)
    assert not shadow.any()
    for k in range(6):
        truth = torch.from_numpy(
            read_mask(tmp_path / "s" / "truth_masks" / f"pose{k + 1}.png") > 127
        )
        tp = float((masks[k] & truth).sum())
        f = 2 * tp / float(masks[k].sum() + truth.sum())
        assert f > 0.93, (k, f)  # a small person (480x384): the lost edge ring weighs more
    # despill: no green excess left on the person's edge
    background = (~masks[0]).float()[None, None]
    edge = masks[0] & torch.nn.functional.max_pool2d(background, 3, 1, 1)[0, 0].bool()
    excess = images[0, 1] - torch.maximum(images[0, 0], images[0, 2])
    assert float(excess[edge].max()) <= 1e-6
