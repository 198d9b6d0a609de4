"""Judge a fitted subject: ``ok``, ``poor_fit`` or ``failed``, with the reason."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from torchfit.pipeline.stages import FAILED_SOLVER_STATUS, StageRecord
from torchfit.status import SubjectStatus

__all__ = ["judge"]


def judge(
    stages: Sequence[StageRecord],
    quality: Mapping[str, Mapping[str, float]],
    max_contour_rms_px: float,
    segmentation_flags: Sequence[str] = (),
) -> tuple[SubjectStatus, str]:
    """A fitted subject's status and message.

    Args:
        stages: the subject's stage records, in order.
        quality: posture name -> ``{"e_P_rms_px": ..., "e_M_px": ...}`` at the end.
        max_contour_rms_px: e_M above which the fit is ``poor_fit``.
        segmentation_flags: what makes the silhouettes doubtful (a posture that does not
            reach the floor, :func:`torchfit.pipeline.prepare.reach_floor`).

    Returns:
        ``FAILED`` when a stage failed or the final cost is not finite; ``POOR_FIT`` when the
        model contour is on average further than ``max_contour_rms_px`` from the person's in
        some posture or when the stage records carry ``flags`` (a posture that disagreed
        with the others and was down-weighted, proportions far from human, scales on their upper
        bounds; see :mod:`torchfit.pipeline.stages`); ``OK`` otherwise (the last stage's
        solver message). Segmentation flags come first: they are the cause of a poor
        contour, not its consequence.
    """
    failed = any(s.status in FAILED_SOLVER_STATUS for s in stages) or not math.isfinite(
        stages[-1].cost
    )
    message = stages[-1].message
    if failed:
        return SubjectStatus.FAILED, message
    if segmentation_flags:
        return SubjectStatus.POOR_FIT, "; ".join(segmentation_flags)
    worst = max(quality, key=lambda key: quality[key]["e_M_px"])
    if quality[worst]["e_M_px"] > max_contour_rms_px:
        return SubjectStatus.POOR_FIT, (
            f"model contour {quality[worst]['e_M_px']:.1f} px (RMS) from the "
            f"person's in {worst}: check the segmentation in the overlays"
        )
    flags = [f for s in stages for f in s.flags]
    if flags:
        return SubjectStatus.POOR_FIT, "; ".join(flags)
    return SubjectStatus.OK, message
