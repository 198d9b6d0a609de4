"""benchmarks/posture_joints.py on a "fit" whose answer is known: the truth's joints are the
template's own posed ones, moved along the camera's ray by a known depth, its head top lowered
by a known height in posture 1."""

import csv
import json
import math

import numpy as np
import pytest
import torch
import yaml
from scripts import load_script

from torchfit.body.measure import measure_model

DEPTH = 3.0  # the camera's distance from the world origin, along world y


@pytest.fixture(scope="module")
def tool():
    return load_script("benchmarks/posture_joints.py")


def _params(model):
    """params.json of the template's own body standing in a T-pose, and in posture 1 with the
    left hip flexed (its foot lifted off the floor)."""
    scales = {name: [1.0, 1.0, 1.0] for name in model.template.segments}
    root = {"root_rotation": np.eye(3).tolist(), "root_translation_xy": [0.0, 0.0]}
    arms = {f"{side}_shoulder_abduct": math.pi / 2 for side in "lr"}
    poses = {
        "pose4": {"joint_angles": arms, **root},
        "pose1": {"joint_angles": {"l_hip_flexion": 0.5}, **root},
    }
    return {"template": "mpeg4_full", "segment_scales": scales, "poses": poses}


def test_errors_split_along_and_across_the_rays(tool, model, tmp_path, capsys):
    data, run = tmp_path / "data", tmp_path / "run"
    (data / "s").mkdir(parents=True)
    (run / "s").mkdir(parents=True)
    camera = {  # looking along world +y from y = -DEPTH, 1 m above the floor
        "image_size": [640, 480],
        "K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]],
        "dist": [0, 0, 0, 0, 0],
        "R": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
        "t": [0, 1, DEPTH],
    }
    (data / "s" / "camera.yaml").write_text(yaml.safe_dump(camera))
    params = _params(model)
    (run / "s" / "params.json").write_text(json.dumps(params))
    ones = torch.ones(1, len(model.template.segments), 3, dtype=model.dtype)
    height = float(measure_model(model, ones)["height_m"][0])
    (run / "s" / "measurements.json").write_text(json.dumps({"height_m": height}))
    with open(run / "summary.csv", "w", newline="") as f:
        csv.writer(f).writerows([["subject", "status"], ["s", "ok"]])
    truth = {}
    for pose in ("pose1", "pose4"):
        posed = tool.posed_joints(model, params, pose)
        # the truth 5 cm nearer the camera than the fit in posture 4 (world -y), the same in 1
        shift = np.array([0.0, 0.05 if pose == "pose4" else 0.0, 0.0])
        truth[pose] = {n: (posed[n] - shift).tolist() for n in [*tool.JOINTS, "head_top"]}
    truth["pose1"]["head_top"][2] -= 0.02  # the true body folds 20 mm in posture 1
    (data / "s" / "truth.json").write_text(json.dumps({"joints_world": truth, "height_m": height}))
    assert tool.main(["--data", str(data), "--run", str(run)]) == 0
    out = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines()}
    # posture 4: 50 mm, nearly all along the rays (the joints are close to the camera's axis)
    mean, along, across, signed = map(float, out["pose4"][2:6])
    assert mean == pytest.approx(50.0, abs=0.05)
    assert 45.0 < along <= 50.0 and across < 20.0 and signed == pytest.approx(along, abs=0.05)
    # posture 1: no joint error, and the flexed leg's sole well off the floor
    assert float(out["pose1"][2]) == 0.0
    assert float(out["pose1"][7]) > 50.0
    # the head top 20 mm above the truth's; the fit stands as tall as its height, the truth
    # 20 mm less; posture 4's head tops agree (the shift was along the ray)
    assert float(out["pose1"][12]) == pytest.approx(20.0, abs=0.05)
    assert float(out["pose1"][13]) == pytest.approx(0.0, abs=0.05)
    assert float(out["pose1"][15]) == pytest.approx(20.0, abs=0.05)
    assert float(out["pose4"][12]) == pytest.approx(0.0, abs=0.05)
