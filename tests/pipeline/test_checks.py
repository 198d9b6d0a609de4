"""The judge's checks without the truth: ANSUR II proportions, scales on bounds, flags."""

import csv
import importlib.util
import math
from pathlib import Path

import pytest

from torchfit.pipeline.checks import (
    PROPORTIONS_CSV,
    Outlier,
    Proportion,
    bound_flags,
    load_proportions,
    population_ranges,
    proportion_flags,
    proportion_outliers,
    root_bound_flags,
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
    for row in table.values():
        assert row.p0_5 < row.p1 < row.gmean < row.p99 < row.p99_5
    arm = table["arm_span_m"]
    assert arm.convention == "same" and 0.9 < arm.p1 < 1.0 < arm.p99 < 1.15
    assert {r.convention for k, r in table.items() if k != "arm_span_m"} == {"template"}


def test_population_ranges_put_the_template_at_the_mean_where_definitions_differ():
    table = {
        "arm_span_m": Proportion("same", 0.95, 0.96, 1.03, 1.10, 1.11),
        "thigh_m": Proportion("template", 0.21, 0.22, 0.25, 0.28, 0.29),
    }
    ranges = population_ranges({"arm_span_m": 1.01, "thigh_m": 0.24}, table)
    assert ranges["arm_span_m"] == (0.96, 1.10)  # read as it is
    lo, hi = ranges["thigh_m"]
    assert lo == pytest.approx(0.22 * 0.24 / 0.25) and hi == pytest.approx(0.28 * 0.24 / 0.25)


def test_outliers_name_the_nearer_end_of_the_range():
    ranges = {"thigh_m": (0.21, 0.27), "forearm_m": (0.12, 0.16)}
    body = {"height_m": 2.0, "thigh_m": 0.56, "forearm_m": 0.23, "upper_arm_m": 1.0}
    out = proportion_outliers(body, ranges)
    assert [(o.key, o.bound) for o in out] == [("thigh_m", 0.27), ("forearm_m", 0.12)]
    assert out[0].ratio == pytest.approx(0.28)
    assert out[0].describe().startswith("thigh / height 0.2800 above the 99th percentile 0.2700")
    assert "(+3.7 %;" in out[0].describe()
    assert out[1].describe().startswith("forearm / height 0.1150 below the 1st percentile 0.1200")
    assert "(-4.2 %;" in out[1].describe()
    assert proportion_outliers({**body, "thigh_m": 0.5, "forearm_m": 0.3}, ranges) == []


def test_the_shoulder_width_is_judged_by_the_hard_limits_only():
    ranges = {"shoulder_width_m": (0.175, 0.221), "forearm_m": (0.125, 0.155)}
    broad = {"height_m": 1.62, "shoulder_width_m": 0.3619, "forearm_m": 0.23}  # 0.2234
    assert proportion_outliers(broad, ranges) == []
    flagged = proportion_outliers(broad, ranges, exempt=())
    assert [o.key for o in flagged] == ["shoulder_width_m"]
    # the hard limits still hold it: 0.30 of the height is no human shoulder width
    assert proportion_flags({"height_m": 1.62, "shoulder_width_m": 0.486})
    assert not proportion_flags(broad)


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


def test_postures_on_the_protocols_translation_or_yaw_limit():
    on_mark = {"tx": 0.03, "ty": -0.149, "yaw": math.radians(14.9), "roll": 0.0, "pitch": 0.09}
    off = {"tx": -0.15, "ty": 0.02, "yaw": 0.0, "roll": 0.0, "pitch": 0.0}
    turned = {"tx": 0.0, "ty": 0.0, "yaw": math.radians(-15.0), "roll": 0.0, "pitch": -0.09}
    flags = root_bound_flags({1: on_mark, 2: off, 4: turned}, 0.15, 15.0)
    assert flags == [
        "pose2: the floor translation ended on its 0.15 m limit (fit.translation_max_m)",
        "pose4: the yaw ended on its 15 deg limit (fit.yaw_max_deg) (2 postures on a limit: the "
        "person stood off the floor mark or turned, or the fit could not place them)",
    ]
    # one posture on a limit is no flag (good fits have one), nor are the tilts on their
    # 5 deg bound (0.087 rad): the pitch is along the line of sight in a facing posture
    assert root_bound_flags({1: on_mark, 2: off}, 0.15, 15.0) == []
    assert root_bound_flags({1: on_mark, 4: turned}, 0.15, 15.0, min_postures=1) == [
        "pose4: the yaw ended on its 15 deg limit (fit.yaw_max_deg) (1 posture on a limit: the "
        "person stood off the floor mark or turned, or the fit could not place them)"
    ]


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


def test_a_ratio_just_past_its_bound_does_not_print_as_the_bound():
    # the demo's subject_001: 0.22083 against 0.22076 read "0.2208 above ... 0.2208 (+0.0 %"
    text = Outlier("shoulder_width_m", 0.22083, 0.22076).describe()
    assert text.startswith("shoulder_width / height 0.22083 above the 99th percentile 0.22076")
    assert "(+0.03 %;" in text
