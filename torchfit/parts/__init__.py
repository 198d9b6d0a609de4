"""Silhouette part decomposition (the second paper, Jaume-i-Capó et al. 2012).

Posture-5 silhouette → periodic cubic B-spline of its outline → analytic curvature → negative
minima / positive maxima → the paper's rules label back, neck, shoulders, elbows (cut middles)
→ wrists from skin colour → with a calibrated stereo pair, midpoint triangulation → trunk,
upper back, upper arm, forearm and virtual leg. The same 2-D joints give the fit an automatic
initial guess from one camera (:func:`initial_guess_2d`).

Conventions: pixels ``(u, v)`` with ``v`` down; the person faces the camera, so ``l_*`` joints
appear on the image right. World frame metres, z up, floor z = 0.
"""

from torchfit.parts.correspond import corresponding_joints
from torchfit.parts.curve import (
    ContourSpline,
    CurvatureExtremum,
    curvature_extrema,
    fit_contour_spline,
)
from torchfit.parts.decompose import decompose_cactus, leg_gap_top, offsets_from_options
from torchfit.parts.errors import PartsError
from torchfit.parts.initial_guess import InitialGuess2D, PostureExtents, initial_guess_2d
from torchfit.parts.options import PartsOptions
from torchfit.parts.rules import RULE_NAMES, Cut, JointOffsets, Labelling, label_cactus
from torchfit.parts.stereo import (
    STEREO_MEASUREMENT_KEYS,
    pixel_rays,
    project_joints,
    stereo_measurements,
    triangulate_midpoint,
    undistort_pixels,
)
from torchfit.parts.wrists import Ellipse, SkinModel, find_wrists, hand_ellipse

__all__ = [
    "PartsError",
    "PartsOptions",
    "ContourSpline",
    "CurvatureExtremum",
    "fit_contour_spline",
    "curvature_extrema",
    "Cut",
    "JointOffsets",
    "Labelling",
    "RULE_NAMES",
    "label_cactus",
    "Ellipse",
    "SkinModel",
    "hand_ellipse",
    "find_wrists",
    "decompose_cactus",
    "leg_gap_top",
    "offsets_from_options",
    "undistort_pixels",
    "pixel_rays",
    "triangulate_midpoint",
    "stereo_measurements",
    "STEREO_MEASUREMENT_KEYS",
    "corresponding_joints",
    "project_joints",
    "InitialGuess2D",
    "PostureExtents",
    "initial_guess_2d",
]
