"""One frame of silhouette tracking for a batch of sequences: an LM over the pose only.

Parameters per row (one sequence's frame): ``[root_translation (3), root_rotation (3,
axis-angle), joint_angles (Q)]``; the segment scales are fixed (the fitted model's). The
residuals are the fit's (:mod:`torchfit.fit.residuals`): e_P, each person contour pixel's
distance to the model contour over ``sqrt(|C_P|)``, and the person's contour distance map
sampled at the model contour points (e_M per point, over ``sqrt(|C_M|)``), plus a temporal
term ``w ⊙ (x - x_pred)`` towards the prediction (:mod:`torchfit.track.tracker`), a soft floor
contact of the lowest sole point, a pull of the twists towards neutral and one of the limb
joints' depths (along their camera rays, from the shoulder or hip) towards the prediction's.
Joint limits are the solver's bounds. The discrete model-contour choice
(:func:`torchfit.fit.model_contour.select_contour`) is made at the start of each of ``rounds``
solves. The residuals and their closed-form Jacobian are :mod:`torchfit.track.residual`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchfit.body.model import BodyModel
from torchfit.camera import Camera, project_points
from torchfit.fit.model_contour import EdgeSampler, select_contour
from torchfit.fit.options import image_scale
from torchfit.fit.person import PersonData
from torchfit.solver import LMOptions, levenberg_marquardt
from torchfit.track.options import PoseLayout, TrackOptions
from torchfit.track.residual import _JACOBIANS, _depth_target, _FrameResidual

__all__ = ["TrackOptions", "FrameResult", "PoseLayout", "solve_frame"]


@dataclass
class FrameResult:
    """One frame of B sequences.

    Attributes:
        x: (B, P) fitted pose rows.
        cost: (B,) final cost ``0.5 |r|²``.
        reference_rms: (B,) RMS of e_P in reference pixels (``reference_px_per_m``): how far
            the person contour lies from the model's, as the tracker's limits read it.
        iterations: (B,) LM iterations over all rounds.
        image_scale: (B,) reference pixels per image pixel.
    """

    x: torch.Tensor
    cost: torch.Tensor
    reference_rms: torch.Tensor
    iterations: torch.Tensor
    image_scale: torch.Tensor

    @property
    def contour_rms(self) -> torch.Tensor:
        """(B,) :attr:`reference_rms` in the image's pixels (what the records report)."""
        return self.reference_rms / self.image_scale


def solve_frame(
    model: BodyModel,
    scales: torch.Tensor,
    person: PersonData,
    layout: PoseLayout,
    x0: torch.Tensor,
    prediction: torch.Tensor,
    options: TrackOptions,
    sampler: EdgeSampler | None = None,
    iterations: torch.Tensor | None = None,
) -> FrameResult:
    """Fit the pose of one frame of each of B sequences.

    Args:
        model: the body model.
        scales: (B, S, 3) the fitted segment scales of each sequence's subject.
        person: the frame's person data (J = 1 silhouette per row).
        layout: the pose layout (its bounds; the weights are taken from ``options``).
        x0: (B, P) start.
        prediction: (B, P) the temporal term's target.
        options: tracker options.
        sampler: edge sampler of the model mesh (made when None).
        iterations: (B,) LM iterations per contour choice of each row, where rows want
            different numbers (default: ``options.iterations``); a row's solve is the one it
            would have alone.
    """
    sampler = sampler or EdgeSampler(model.faces, options.samples_per_edge)
    layout = layout.for_options(options)  # the weights are this solve's (a restart's, ...)
    camera: Camera = person.camera
    x = layout.clip(x0)
    done = torch.zeros(x.shape[0], dtype=torch.long)  # LM iterations made, per row
    lm = LMOptions(
        max_iter=options.iterations if iterations is None else int(iterations.max()),
        fold_batch=False,
        min_diag=options.min_diag,
        initial_damping=options.initial_damping,
        ftol=options.ftol,
        xtol=options.xtol,
    )
    cost = torch.zeros(x.shape[0], dtype=x.dtype)
    # the limbs' depth targets at the prediction; where the solve starts there, from its
    # first kinematics pass
    at_prediction = torch.equal(x, prediction)
    target = None if at_prediction else _depth_target(model, scales, camera, prediction, layout)
    scale = image_scale(camera, options.reference_px_per_m).to(x)
    residual = problem = None
    every = torch.arange(model.template.vertices.shape[0], device=x.device)
    rows = torch.arange(x.shape[0], device=x.device)
    for _ in range(options.rounds):
        # one kinematics pass of every vertex serves the contour choice and the solve's start
        # (the last solve's, where it ended on its accepted trial point)
        with torch.no_grad():
            whole = None if problem is None else problem.pass_at(x, every)
            if whole is None:
                t, r, q = PoseLayout.split(x)
                whole = model.pose_pass(scales, q, t, r, every)
            if target is None:
                target = _depth_target(model, scales, camera, prediction, layout, whole[2].vertices)
            pix = project_points(whole[2].vertices, camera)
        sel = select_contour(
            sampler, pix, person.contours[0], person.valid[0], camera.image_size, 1.0
        )
        problem = _FrameResidual(
            model, scales, person, layout, prediction, sampler, sel, target, scale
        )
        problem.start_from(x, rows, whole, jacobian=options.jacobian == "analytic")
        res = levenberg_marquardt(
            problem,
            x,
            lm,
            jacobian=_JACOBIANS[options.jacobian](problem)
            if options.jacobian in _JACOBIANS
            else options.jacobian,
            lower=layout.lower,
            upper=layout.upper,
            indexed=True,
            max_iter=iterations,
        )
        x, cost, residual = res.x, res.cost, res.residual
        done += res.n_iter.cpu().long()
    # the solver's last residual is the one at x: e_P leads it, already over sqrt(|C_P|), in
    # reference pixels
    e_p = residual[:, : person.contours[0].shape[1]]
    rms = (e_p * e_p).sum(1).sqrt()
    return FrameResult(x=x, cost=cost, reference_rms=rms, iterations=done, image_scale=scale)
