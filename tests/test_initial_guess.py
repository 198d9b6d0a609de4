"""The automatic initial guess (fit.initial_guess: parts) on subjects rendered from the template."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from template_subjects import make_template_subject

from torchfit.camera import stack_cameras
from torchfit.config import Config, replace_keys
from torchfit.errors import ConfigError
from torchfit.fit import FitOptions, SilhouetteFit, person_data_from_masks
from torchfit.fit.initial_guess import arm_ratios, parts_start
from torchfit.io.dataset import load_dataset
from torchfit.pipeline import segment_subject

REPO = Path(__file__).resolve().parents[1]
SCALES = (0.92, 1.1)
ONE_STEP = "[{name: all, scales: [all], joints: true, root: true, max_iter: 1}]"


@pytest.fixture(scope="module")
def subjects(tmp_path_factory, model):
    root = tmp_path_factory.mktemp("subjects")
    for k, scale in enumerate(SCALES):
        make_template_subject(root / f"s{k}", model, scale=scale, seed=k + 10)
    return root


@pytest.fixture(scope="module")
def segmented(subjects):
    # without the outline test: on these small renders (the body about 200 px tall, arms 8 px
    # thick) removing the outline's mixed pixels moves the upper-arm estimate by up to 10 %
    # (benchmarks/RESULTS.md, "Segmentation speed, and the outline's mixed pixels"); the
    # estimate's own accuracy is what this file tests
    config = replace_keys(Config(), {"segmentation.edge_width": 0})
    found = load_dataset(subjects)
    pairs = [segment_subject(s, config) for s in found]
    images = torch.stack([i for i, _, _ in pairs])
    masks = torch.stack([m for _, m, _ in pairs])
    return found, images, masks


def _fit(model, found, masks, fit_config=None):
    person = person_data_from_masks(masks, stack_cameras([s.camera for s in found]))
    return SilhouetteFit(model, person, fit_config or FitOptions())


def test_parts_start_recovers_scale_root_and_upper_arm(model, segmented):
    found, _, masks = segmented
    fit = _fit(model, found, masks)
    # no images: the template renders have no skin colour of their own, so there are no
    # wrists to find and the forearm keeps the overall scale
    x, info = parts_start(fit, masks)
    assert torch.all(x >= fit.lower) and torch.all(x <= fit.upper)
    upper = fit.layout.names.index("scale:upperarm:z")
    for i, scale in enumerate(SCALES):
        assert info[i].source == "parts", info[i]
        assert info[i].scale == pytest.approx(scale, rel=0.015)
        # every segment starts at the overall scale, the upper arm at its own estimate
        others = [k for k in range(fit.layout.num_scale_params) if k != upper]
        assert torch.allclose(x[i, others], torch.tensor(info[i].scale, dtype=x.dtype))
        assert info[i].upperarm == pytest.approx(scale, rel=0.04)
        assert float(x[i, upper]) == pytest.approx(info[i].upperarm)
        assert info[i].forearm is None
        # the subjects stand on the mark in every posture
        for j in fit.poses:
            tx = fit.layout.names.index(f"pose{j}:tx")
            assert float(x[i, tx].abs()) < 0.02 and float(x[i, tx + 1].abs()) < 0.02, j


def test_arm_ratios_average_sides_and_refuse_implausible_arms():
    model = {
        "l_shoulder": (0, 0), "l_elbow": (100, 0), "l_wrist": (100, -80),
        "r_shoulder": (0, 0), "r_elbow": (-100, 0), "r_wrist": (-100, -80),
    }  # fmt: skip
    person = {k: np.asarray(v, dtype=float) * 1.1 for k, v in model.items()}
    person["r_elbow"] = np.array([-120.0, 0.0])  # upper arms 1.1 and 1.2 -> 1.15
    person["r_wrist"] = np.array([-120.0, -88.0])
    ratio, notes = arm_ratios(person, model)
    assert ratio == pytest.approx({"upperarm": 1.15, "forearm": 1.1}) and notes == []
    # wrists cut short: forearm 0.9 against upper arm 1.15, a proportion of 0.78 -> dropped
    short = {**person, "l_wrist": np.array([110.0, -72.0]), "r_wrist": np.array([-120.0, -72.0])}
    ratio, notes = arm_ratios(short, model)
    assert set(ratio) == {"upperarm"} and "wrists misplaced" in notes[0]
    # an elbow cut twice as far out as a body allows
    far = {**person, "l_elbow": np.array([250.0, 0.0]), "r_elbow": np.array([-250.0, 0.0])}
    ratio, notes = arm_ratios(far, model)
    assert "upperarm" not in ratio and "upperarm ratio 2.50" in notes[0]
    # missing wrists: the forearm is simply not estimated
    ratio, notes = arm_ratios({k: v for k, v in person.items() if "wrist" not in k}, model)
    assert set(ratio) == {"upperarm"} and notes == []


def test_parts_start_falls_back_and_says_why(model, segmented):
    found, images, masks = segmented
    broken = masks.clone()
    broken[0, 0] = False  # subject 0: empty posture-1 silhouette
    h, w = broken.shape[-2:]
    broken[1, 4] = False  # subject 1: posture 5 is a box, no cactus to label
    broken[1, 4, h // 4 : 3 * h // 4, w // 3 : 2 * w // 3] = True
    fit = _fit(model, found, masks)
    x, info = parts_start(fit, broken, images)
    assert info[0].source == "template" and "posture 1" in info[0].message
    assert torch.equal(x[0], fit.initial_params()[0])
    assert info[1].source == "parts_extents" and info[1].message.startswith("pose5:")
    assert info[1].upperarm is None and info[1].scale == pytest.approx(SCALES[1], rel=0.015)


def test_parts_start_needs_postures_1_and_5(model, segmented):
    found, _, masks = segmented
    fit = _fit(model, found, masks[:, :3], FitOptions(poses=[1, 2, 3]))
    with pytest.raises(ConfigError, match="posture 5"):
        parts_start(fit, masks[:, :3])


def test_fit_cli_records_the_parts_start(subjects, tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run(
        [
            sys.executable,
            str(REPO / "tools" / "fit.py"),
            "--config",
            str(REPO / "configs" / "demo.yaml"),
            "--data",
            str(subjects),
            "--out",
            str(out),
            *("--set", "fit.initial_guess=parts", "--set", f"fit.stages={ONE_STEP}"),
            *("--set", "fit.contour_stride=4", "--set", "output.overlays=false"),
            *("--set", "output.tensorboard=false"),
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    for k, scale in enumerate(SCALES):
        start = json.loads((out / f"s{k}" / "params.json").read_text())["initial_guess"]
        assert start["source"] == "parts"
        assert start["scale"] == pytest.approx(scale, rel=0.015)
