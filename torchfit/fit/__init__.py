"""The six-posture fit (first paper): parameter layout, person data, pose glue, model
contour, residuals, the problem and its Jacobian, stages, the initial guess and the rendered
MINPACK baseline.

Nothing here reads a config: the pipeline hands in :class:`FitOptions`, :class:`StageOptions`
and :class:`torchfit.solver.LMOptions`.
"""

from torchfit.fit.layout import ROOT_NAMES, SCALE_ALIASES, JointBounds, ParamLayout, ResidualLayout
from torchfit.fit.person import PersonData, person_data_from_masks
from torchfit.fit.pose import DEFAULT_FREE_JOINTS, Poser, euler_rotation
from torchfit.fit.problem import FitOptions, SilhouetteFit
from torchfit.fit.stages import JACOBIANS, StageOptions, solve_stage

__all__ = [
    "ROOT_NAMES",
    "SCALE_ALIASES",
    "DEFAULT_FREE_JOINTS",
    "JACOBIANS",
    "JointBounds",
    "ParamLayout",
    "ResidualLayout",
    "PersonData",
    "person_data_from_masks",
    "Poser",
    "euler_rotation",
    "FitOptions",
    "SilhouetteFit",
    "StageOptions",
    "solve_stage",
]
