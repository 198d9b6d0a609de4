"""The judge's checks without the truth: ANSUR II proportions, scales on bounds, flags."""

import csv
import importlib.util
from pathlib import Path

import pytest

from torchfit.pipeline.checks import (
    PROPORTIONS_CSV,
    bound_flags,
    load_proportions,
    proportion_flags,
)
from torchfit.pipeline.judge import judge
from torchfit.pipeline.stages import StageRecord
from torchfit.status import SubjectStatus

ROOT = Path(__file__).resolve().parents[2]
GOOD = {"pose1": {"e_P_rms_px": 1.0, "e_M_px": 2.0}}
# design.md's example subject (joint-centre definitions of the model)
HUMAN = {
    "height_m": 1.78,
    "arm_span_m": 1.80,
    "lower_leg_m": 0.52,
    "thigh_m": 0.45,
    "upper_arm_m": 0.30,
    "forearm_m": 0.26,
    "shoulder_width_m": 0.37,
}


def test_a_human_body_passes_and_a_dragged_arm_does_not():
    assert proportion_flags(HUMAN) == []
    # the case: arm span 2.83 m for a 1.77 m woman
    flags = proportion_flags({**HUMAN, "height_m": 1.77, "arm_span_m": 2.83})
    assert len(flags) == 1 and flags[0].startswith("arm_span / height 1.599 outside 0.932-1.144")


def test_the_table_holds_every_ratio_it_is_read_for():
    table = load_proportions()
    assert set(table) == {
        "arm_span_m",
        "upper_arm_m",
        "forearm_m",
        "lower_leg_m",
        "thigh_m",
        "shoulder_width_m",
    }
    lo, hi = table["arm_span_m"]
    assert 0.9 < lo < 1.0 < hi < 1.15


def test_committed_table_matches_the_derivation(shared_data):
    spec = importlib.util.spec_from_file_location("mp", ROOT / "tools" / "make_proportions.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    rows = module.derive(shared_data / "ansur2")
    with PROPORTIONS_CSV.open(newline="") as f:
        assert list(csv.DictReader(f)) == rows


def test_scales_on_their_upper_bound():
    flags = bound_flags([1.0, 1.89, 0.4], ["a:x", "b:y", "c:z"], (0.4, 1.9))
    assert flags == ["scale b:y = 1.89 at its upper bound 1.9"]


def test_flags_make_a_poor_fit_with_their_message():
    records = [StageRecord("a", "XTOL", "x", 20.0, 5), StageRecord("b", "FTOL", "done", 9.0, 7)]
    assert judge(records, GOOD, 15.0) == (SubjectStatus.OK, "done")
    records[-1].flags = ["pose4 down-weighted: contour rms 14.2 px vs median 2.1"]
    status, message = judge(records, GOOD, 15.0)
    assert status is SubjectStatus.POOR_FIT
    assert message == "pose4 down-weighted: contour rms 14.2 px vs median 2.1"
    assert records[-1].to_dict()["flags"] == [message]
    assert "flags" not in records[0].to_dict()


@pytest.mark.parametrize("key", ["upper_arm_m", "forearm_m", "lower_leg_m", "thigh_m"])
def test_a_limb_half_again_too_long_is_flagged(key):
    flags = proportion_flags({**HUMAN, key: HUMAN[key] * 1.6})
    assert len(flags) == 1 and flags[0].startswith(key[:-2])
