"""A proportion outside the population's range stands where the images show it.

The template rendered with shoulders broader than any in ANSUR II (shoulder width / height
13 % above the 99th percentile): the four facing postures show where the arms hang, so the
fit follows the images and stays ``ok``, with a note saying what is unusual and what pinning
it at the percentile costs the images (:func:`torchfit.fit.evidence.pinning_cost`).
"""

import json
from pathlib import Path

import pytest
import torch
from template_subjects import make_template_subject

from torchfit.body.measure import measure_model
from torchfit.config import load_config, replace_keys
from torchfit.pipeline import run
from torchfit.pipeline.checks import population_ranges

REPO = Path(__file__).resolve().parents[2]
CLAVICLE = 1.3  # the clavicle's width scale: shoulder width / height about 0.25


def _broad_shoulders(model) -> torch.Tensor:
    scales = torch.ones(1, model.num_segments, 3, dtype=model.dtype)
    groups = model.template.scale_groups
    for s in range(model.num_segments):
        if groups[int(model.template.segment_group[s])] == "clavicle":
            scales[0, s, 1] = CLAVICLE
    return scales


def _ratios(model, scales) -> dict[str, float]:
    m = measure_model(model, scales)
    return {k: float(v[0] / m["height_m"][0]) for k, v in m.items()}


@pytest.mark.slow
def test_unusual_shoulders_the_images_show_stay_ok_with_a_note(tmp_path, model):
    scales = _broad_shoulders(model)
    make_template_subject(tmp_path / "data" / "broad", model, seed=3, scales=scales)
    ranges = population_ranges(_ratios(model, torch.ones_like(scales)))
    truth = _ratios(model, scales)
    assert truth["shoulder_width_m"] > ranges["shoulder_width_m"][1] * 1.1  # truly unusual
    others = [k for k in ranges if k != "shoulder_width_m"]
    assert all(ranges[k][0] < truth[k] < ranges[k][1] for k in others)

    config = load_config(REPO / "configs" / "benchmark.yaml")
    config = replace_keys(
        config,
        {
            "data.root": str(tmp_path / "data"),
            "output.overlays": False,
            "output.tensorboard": False,
        },
    )
    run(config, tmp_path / "run")
    folder = tmp_path / "run" / "broad"
    measured = json.loads((folder / "measurements.json").read_text())
    last = json.loads((folder / "params.json").read_text())["stages"][-1]
    fitted = measured["shoulder_width_m"] / measured["height_m"]
    assert fitted > ranges["shoulder_width_m"][1], (fitted, ranges["shoulder_width_m"])
    assert measured["status"] == "ok", last
    notes = [n for n in last.get("notes", []) if n.startswith("shoulder_width / height")]
    assert len(notes) == 1 and notes[0].endswith("(the images show it)"), last
    assert not any(f.startswith("shoulder_width") for f in last.get("flags", []))
