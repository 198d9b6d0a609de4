"""The tracker's options and where the pose lives in a parameter row (:class:`PoseLayout`)."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Literal, get_args

import torch

from torchfit.body.model import BodyModel
from torchfit.errors import ConfigError

__all__ = ["TrackOptions", "PoseLayout", "LOST_CONFIDENCE"]

#: a frame with no good frame before it is lost when its contour RMS exceeds this many
#: ``confidence_px`` (its confidence is then under 0.1): the start is tried again from the
#: T-pose, and a first frame still that far off is ``uncertain``
LOST_CONFIDENCE = 3.0

#: limb joint whose depth the ``temporal_depth`` term holds -> the joint its limb hangs from.
_DEPTH_JOINTS = {
    f"{s}_{j}": f"{s}_{base}"
    for s in ("l", "r")
    for j, base in (("elbow", "shoulder"), ("wrist", "shoulder"), ("knee", "hip"), ("ankle", "hip"))
}


#: the tracker's Jacobians (:mod:`torchfit.track.residual`) and the solver's own
Jacobian = Literal["analytic", "batched", "forward", "reverse", "autograd", "numeric"]
_JACOBIAN_NAMES = get_args(Jacobian)
#: options that count something (each at least 1)
_COUNTS = ("iterations", "rounds", "samples_per_edge", "contour_stride", "recover_every")
#: numeric options -> whether they must be > 0 (else >= 0)
_NUMBERS = {
    "initial_damping": True,
    "min_diag": True,
    "ftol": False,
    "xtol": False,
    "temporal_translation": False,
    "start_translation": False,
    "temporal_rotation": False,
    "temporal_joints": False,
    "floor_weight": False,
    "twist_weight": False,
    "temporal_depth": False,
    "recover_factor": True,
    "recover_min_px": False,
    "confidence_px": True,
    "turn_velocity": False,
    "turn_dead_deg": False,
    "recover_arms_deg": False,
    "bridge_min": False,
}


@dataclass(frozen=True)
class TrackOptions:
    """Options of the tracker.

    Attributes:
        iterations: LM iterations per contour choice (a recovery's solve takes twice as
            many, the first frame's, from the neutral pose, three times as many).
        rounds: contour choices (each followed by an LM solve) per frame. Three choices of one
            iteration each, started with ``initial_damping`` 0.1, track the thirty development
            clips of ``benchmarks/track_clips.py --clips wide`` as well as three of three
            started at the solver's 1e-3 (135.8 against 137.6 mm on average) in about 0.6 of
            the time: a frame's solves are near their minimum, and with little damping two in
            three of their first trial steps were rejected.
        temporal_translation: temporal weight of the root translation, pixels per metre. The
            contour is weighed as its RMS, and a silhouette tells the body's distance only
            through its size, which a lean in depth fakes: 1 m of depth moves the RMS by a few
            pixels, so a stiff pull (100) held the root where the last frame left it while the
            person walked or jumped 10-50 cm along the camera ray.
        start_translation: the first frame's pull of the root towards its placement, pixels
            per metre (the placement is measured on the silhouette: its lowest pixel on the
            floor, or its size; with the tracker's weaker pull the floor term drew a start in
            mid-jump down).
        temporal_rotation: temporal weight of the root rotation, pixels per radian.
        temporal_joints: temporal weight of the joint angles, pixels per radian.
        samples_per_edge: model contour candidates per mesh edge.
        recover_factor: a frame whose contour RMS exceeds ``recover_factor`` times the
            sequence's running median (and ``recover_min_px``) is re-initialised from the last
            good frame.
        recover_min_px: see ``recover_factor``.
        recover_every: in a stretch of frames over their limit (``uncertain`` ones), the
            first ``recover_every - 1`` and then every ``recover_every``-th are solved again
            from the last good frame, the others once (1: every frame). A re-start from a pose
            that grows staler each frame seldom fits in a long stretch and costs a second
            solve; tried now and then, it still brings the model back within
            ``recover_every`` frames of the silhouette being right again.
        recover_arms_deg: a frame solved again from the last good frame is also solved (in
            the same batch) from its own pose with both arms raised sideways to this many
            degrees (shoulder abduction), the best contour kept: an arm left inside the body's
            outline gets no pull from the silhouette's arm outside it (0: off).
        confidence_px: contour RMS at which the confidence is 0.5.
        floor_weight: pull of the lowest sole point towards the floor (z = 0), pixels per
            metre (a soft contact: someone jumping leaves the floor at that cost).
        contour_stride: use every n-th person contour pixel in e_P.
        distance_margin_px: the person's distance map is computed on the box around the
            silhouettes grown by this many pixels (exact there; beyond it a bound, see
            :func:`torchfit.fit.person.person_data_from_masks`); None: the whole image.
        twist_weight: pull of the twists (DOFs named ``*twisting`` and ``*torsion``)
            towards neutral (0), pixels per radian: a silhouette hardly shows a limb turning
            about itself, and a twist left free drifts frame after frame (0 turns it off).
        temporal_depth: temporal weight of each limb joint's depth (elbows, wrists, knees,
            ankles), pixels per metre: its offset from the joint its limb hangs from (shoulder,
            hip) along its camera ray (the prediction's), towards the prediction's (from the
            limb's own joint, not the root: the trunk leaning or turning stays free). A
            silhouette shows a limb across the ray and hides it along the ray (an arm in front
            of or behind the body), where the angle pulls alone let it drift from frame to
            frame; this holds only that direction, so a limb still follows what the
            silhouette shows (0 turns it off).
        velocity_damping: the prediction is ``x_{t-1} + velocity_damping (x_{t-1} - x_{t-2})``
            (1: constant velocity, 0: the last pose).
        turn_velocity: the prediction continues the body's turn about the vertical: its root
            rotation is the last one turned by ``turn_velocity`` times the recent turn rate
            (radians per frame, smoothed and shrunk by ``turn_dead_deg``). A silhouette looks
            the same from the front and from the back: a person turning through the side view
            can be followed on either way out of it, and with the last pose as the prediction
            the model turned back while the person turned on (0 turns it off).
        turn_smoothing: the turn rate is the exponential average ``a rate + (1 - a) turn``
            of the frames' turns, ``a`` this (reset to 0 after a frame not ``ok``).
        turn_dead_deg: degrees per frame taken off the turn rate's size before it is
            continued, so that a standing person's heading noise is not carried on.
        ftol, xtol: the solver's stopping tolerances (:class:`torchfit.solver.LMOptions`):
            a row stops before ``iterations`` once its relative cost reduction or its
            relative step falls below them.
        min_diag: floor of the solver's scaling (:attr:`torchfit.solver.LMOptions.min_diag`).
        initial_damping: the solver's damping at the start of each solve
            (:attr:`torchfit.solver.LMOptions.initial_damping`, relative to the scaling;
            the solver's own default, 1e-3, overshoots from a frame's warm start).
        jacobian: ``analytic`` (the pose derivatives in closed form, one model call per
            Jacobian: the fastest), ``batched`` (forward differences, all the perturbed rows in
            one model call) or a solver Jacobian (``forward``, ``numeric``).
        reference_px_per_m: the contour terms (e_P, e_M) are in pixels of a camera that sees
            this many pixels per metre at the person (1 m above the floor mark,
            :func:`torchfit.fit.options.pixels_per_metre`), as the fit's are
            (``fit.reference_px_per_m``): the weights above ("pixels per ...") and the pixel
            limits ``recover_min_px`` and ``confidence_px`` then mean the same on a camera of
            any resolution. ``contour_rms`` in the frame records stays in the image's pixels;
            ``distance_margin_px`` is the image's. ``None``: everything in the image's pixels.
        bridge_min: with background subtraction, a frame whose shadow test removed pixels
            between the body above them and a part of the person cut off below them, at least
            this fraction of the silhouette's area, gets a second silhouette with them given
            back (``segmentation.shadow_bridge``); the tracker takes that silhouette where
            most of what it adds lies on the body as the predicted pose draws it, or where a
            solve to it fits better (:mod:`torchfit.track.silhouettes`). Light trousers before
            a light wall are an attenuated copy of it, and the first silhouette ends at the
            hips; a shadow on the floor between the feet is bridged too, and stays out (0:
            off).
    """

    iterations: int = 1
    rounds: int = 3
    temporal_translation: float = 20.0
    start_translation: float = 100.0
    temporal_rotation: float = 5.0
    temporal_joints: float = 2.0
    samples_per_edge: int = 2
    recover_factor: float = 2.5
    recover_min_px: float = 4.0
    recover_every: int = 4
    recover_arms_deg: float = 45.0
    confidence_px: float = 6.0
    floor_weight: float = 30.0
    min_diag: float = 1e-6
    initial_damping: float = 0.1
    contour_stride: int = 3
    distance_margin_px: int | None = 48
    jacobian: Jacobian = "analytic"
    ftol: float = 1e-3
    xtol: float = 1e-3
    velocity_damping: float = 0.0
    twist_weight: float = 20.0
    temporal_depth: float = 15.0
    turn_velocity: float = 1.0
    turn_smoothing: float = 0.6
    turn_dead_deg: float = 2.0
    reference_px_per_m: float | None = 210.0
    bridge_min: float = 0.05

    def __post_init__(self) -> None:
        ref = self.reference_px_per_m
        if ref is not None and not (math.isfinite(ref) and ref > 0):
            raise ConfigError(
                f"track.reference_px_per_m: expected a number > 0 or null, got {ref!r}"
            )
        for name in _COUNTS:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"track.{name}: expected an integer >= 1, got {value!r}")
        for name, positive in _NUMBERS.items():
            value = getattr(self, name)
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            ok = ok and math.isfinite(value) and (value > 0 if positive else value >= 0)
            if not ok:
                bound = "> 0" if positive else ">= 0"
                raise ConfigError(f"track.{name}: expected a number {bound}, got {value!r}")
        a = self.turn_smoothing
        if isinstance(a, bool) or not isinstance(a, (int, float)) or not 0 <= a <= 1:
            raise ConfigError(f"track.turn_smoothing: expected a number in [0, 1], got {a!r}")
        margin = self.distance_margin_px
        if margin is not None and (
            isinstance(margin, bool) or not isinstance(margin, int) or margin < 0
        ):
            raise ConfigError(
                f"track.distance_margin_px: expected an integer >= 0 or null, got {margin!r}"
            )
        if self.jacobian not in _JACOBIAN_NAMES:
            raise ConfigError(
                f"track.jacobian: expected one of {', '.join(_JACOBIAN_NAMES)},"
                f" got {self.jacobian!r}"
            )


class PoseLayout:
    """Where the pose lives in a parameter row, its bounds and its temporal weights."""

    def __init__(self, model: BodyModel, options: TrackOptions) -> None:
        q = model.num_dofs
        kw = {"dtype": model.dtype, "device": model.device}
        inf = torch.full((6,), float("inf"), **kw)
        self.num_params = 6 + q
        self.lower = torch.cat([-inf, model.joint_lower.to(**kw)])
        self.upper = torch.cat([inf, model.joint_upper.to(**kw)])
        self._twist = torch.tensor([n.endswith(("twisting", "torsion")) for n in model.dof_names])
        #: (2, K) per limb joint and the joint its limb hangs from, the vertex of the segment
        #: starting there nearest to the joint (it moves with the joint)
        t = model.template

        def near(joint: str) -> int:
            idx = torch.nonzero(t.vertex_segment == t.joints[joint]).flatten()
            return int(idx[t.vertices[idx].norm(dim=1).argmin()])

        pairs = [(near(j), near(b)) for j, b in _DEPTH_JOINTS.items() if {j, b} <= set(t.joints)]
        self.depth_vertices = torch.tensor(pairs, dtype=torch.long).reshape(-1, 2).T.contiguous()
        self._set_weights(options)

    def _set_weights(self, options: TrackOptions) -> None:
        kw = {"dtype": self.lower.dtype, "device": self.lower.device}
        self.floor_weight = options.floor_weight
        self.depth_weight = options.temporal_depth if self.depth_vertices.shape[1] else 0.0
        #: (Q,) pull of each joint angle towards neutral, or None
        self.neutral = (
            (options.twist_weight * self._twist).to(**kw) if options.twist_weight else None
        )
        self.weights = torch.cat(
            [
                torch.full((3,), options.temporal_translation, **kw),
                torch.full((3,), options.temporal_rotation, **kw),
                torch.full((self.num_params - 6,), options.temporal_joints, **kw),
            ]
        )

    def for_options(self, options: TrackOptions) -> PoseLayout:
        """The same layout with the temporal and floor weights of ``options``."""
        other = copy.copy(self)
        other._set_weights(options)
        return other

    @staticmethod
    def split(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(translation, rotation, joint angles) of (B, P) rows."""
        return x[:, :3], x[:, 3:6], x[:, 6:]

    def clip(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` inside the bounds."""
        return torch.maximum(torch.minimum(x, self.upper), self.lower)
