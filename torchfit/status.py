"""The outcome of one subject, shared by the fit run, the benchmark report and the stereo
measurement."""

from __future__ import annotations

from enum import Enum

__all__ = ["SubjectStatus"]


class SubjectStatus(str, Enum):
    """A subject's status, as written to summary.csv, measurements.json and params.json.

    ``OK``: fitted (or measured). ``POOR_FIT``: fitted, but the model contour stays far from
    the person's in some posture (check its overlays). ``FAILED``: no result; the message says
    why. The string values are what the files hold.
    """

    OK = "ok"
    POOR_FIT = "poor_fit"
    FAILED = "failed"

    def __str__(self) -> str:
        return self.value
