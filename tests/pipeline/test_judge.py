"""A fitted subject's status: the rules of torchfit.pipeline.judge on hand-made records."""

import math

from torchfit.pipeline.judge import judge
from torchfit.pipeline.stages import StageRecord
from torchfit.status import SubjectStatus

GOOD = {"pose1": {"e_P_rms_px": 1.0, "e_M_px": 2.0}, "pose2": {"e_P_rms_px": 1.0, "e_M_px": 3.0}}


def stages(status="FTOL", cost=10.0):
    return [StageRecord("a", "XTOL", "x", 20.0, 5), StageRecord("b", status, "done", cost, 7)]


def test_ok_keeps_the_solver_message():
    assert judge(stages(), GOOD, 15.0) == (SubjectStatus.OK, "done")


def test_a_posture_far_from_the_person_is_a_poor_fit_named():
    bad = {**GOOD, "pose2": {"e_P_rms_px": 9.0, "e_M_px": 21.5}}
    status, message = judge(stages(), bad, 15.0)
    assert status is SubjectStatus.POOR_FIT
    assert message.startswith("model contour 21.5 px (RMS) from the person's in pose2")


def test_failed_solver_or_non_finite_cost_fails():
    assert judge(stages("NONFINITE"), GOOD, 15.0)[0] is SubjectStatus.FAILED
    assert judge(stages("LINALG"), GOOD, 15.0)[0] is SubjectStatus.FAILED
    assert judge(stages(cost=math.nan), GOOD, 15.0)[0] is SubjectStatus.FAILED


def test_status_is_a_string_in_files():
    assert str(SubjectStatus.POOR_FIT) == "poor_fit" and SubjectStatus.FAILED == "failed"
