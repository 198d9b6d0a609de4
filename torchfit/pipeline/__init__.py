"""Runs: the fit over a dataset (:func:`run`), the stereo measurement
(:mod:`torchfit.pipeline.stereo`), writing outputs and runtime settings. The config stops
here: below this package, code takes plain arguments and its own options dataclasses."""

from torchfit.pipeline.outputs import SubjectResult, write_summary
from torchfit.pipeline.prepare import PreparedSubject, person_data, segment_subject
from torchfit.pipeline.run import fit_batch, run

__all__ = [
    "run",
    "fit_batch",
    "segment_subject",
    "person_data",
    "PreparedSubject",
    "SubjectResult",
    "write_summary",
]
