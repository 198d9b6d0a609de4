"""benchmarks/leg_parts.py: a lower leg's error split into the ankle's height and the shank's
length, on subjects whose answers are known by construction (the truth's joints those of the
template body the "fit" reports, then the truth's ankles raised)."""

import json

import pytest
from scripts import load_script

from torchfit.body import BodyModel


@pytest.fixture(scope="module")
def tool():
    return load_script("benchmarks/leg_parts.py")


def _truth(tool, model, ankle_up=0.0):
    joints = tool.neutral_joints(model, {n: [1.0, 1.0, 1.0] for n in model.template.segments})
    pose1 = {k: [float(x) for x in v] for k, v in joints.items()}
    for side in "lr":
        pose1[f"{side}_ankle"][2] += ankle_up
    knee = 0.5 * (pose1["l_knee"][2] + pose1["r_knee"][2])
    return {"lower_leg_m": knee, "height_m": pose1["head_top"][2], "joints_world": {"pose1": pose1}}


def test_the_template_against_itself_and_a_higher_ankle(tool, tmp_path):
    model = BodyModel("mpeg4_full")
    fitted = {
        "template": "mpeg4_full",
        "segment_scales": {n: [1.0, 1.0, 1.0] for n in model.template.segments},
    }
    row = tool.subject_row(model, fitted, _truth(tool, model))
    assert all(abs(v) < 1e-9 for v in row.values()), row
    row = tool.subject_row(model, fitted, _truth(tool, model, ankle_up=0.01))
    assert row["ankle"] == pytest.approx(-10.0) and row["shank"] == pytest.approx(10.0)
    assert row["knee"] == pytest.approx(0.0, abs=1e-9) and row["hip"] == pytest.approx(
        0.0, abs=1e-9
    )
    # the command line over a run folder and its set
    for folder in ("run/subject_000", "data/subject_000"):
        (tmp_path / folder).mkdir(parents=True)
    (tmp_path / "run/subject_000/params.json").write_text(json.dumps(fitted))
    truth = _truth(tool, model, ankle_up=0.01)
    (tmp_path / "data/subject_000/truth.json").write_text(json.dumps(truth))
    assert tool.main(["--data", str(tmp_path / "data"), "--run", str(tmp_path / "run")]) == 0
    assert tool.main(["--data", str(tmp_path / "data"), "--run", str(tmp_path / "none")]) == 2
