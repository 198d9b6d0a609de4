"""One frame of silhouette tracking for a batch of sequences: an LM over the pose only.

Parameters per row (one sequence's frame): ``[root_translation (3), root_rotation (3,
axis-angle), joint_angles (Q)]``; the segment scales are fixed (the fitted model's). The
residuals are the fit's (:mod:`torchfit.fit.residuals`): e_P, each person contour pixel's
distance to the model contour over ``sqrt(|C_P|)``, and the person's contour distance map
sampled at the model contour points (e_M per point, over ``sqrt(|C_M|)``), plus a temporal
term ``w ⊙ (x - x_pred)`` towards the (damped) velocity prediction, a soft floor contact
of the lowest sole point, and a prior for what one silhouette does not show: the twists
pulled towards neutral (``twist_weight``; 0 leaves it out). Joint limits are the solver's
bounds. The discrete model-contour choice (:func:`torchfit.fit.model_contour.
select_contour`) is made at the start of each of ``rounds`` solves.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchfit.body.model import BodyModel
from torchfit.camera import Camera, project_points
from torchfit.fit.model_contour import (
    EdgeSampler,
    contour_endpoints,
    point_to_edge_distance,
    select_contour,
)
from torchfit.fit.person import PersonData
from torchfit.image.distance import sample_distance_map
from torchfit.solver import LMOptions, levenberg_marquardt

__all__ = ["TrackOptions", "FrameResult", "PoseLayout", "solve_frame"]

_STEP = 1e-6


@dataclass(frozen=True)
class TrackOptions:
    """Options of the tracker.

    Attributes:
        iterations: LM iterations per contour choice.
        rounds: contour choices (each followed by an LM solve) per frame.
        temporal_translation: temporal weight of the root translation, pixels per metre.
        temporal_rotation: temporal weight of the root rotation, pixels per radian.
        temporal_joints: temporal weight of the joint angles, pixels per radian.
        samples_per_edge: model contour candidates per mesh edge.
        recover_factor: a frame whose contour RMS exceeds ``recover_factor`` times the
            sequence's running median (and ``recover_min_px``) is re-initialised from the last
            good frame.
        recover_min_px: see ``recover_factor``.
        confidence_px: contour RMS at which the confidence is 0.5.
        floor_weight: pull of the lowest sole point towards the floor (z = 0), pixels per
            metre (a soft contact: someone jumping leaves the floor at that cost).
        contour_stride: use every n-th person contour pixel in e_P.
        twist_weight: pull of the twists (DOFs named ``*twisting`` and ``*torsion``)
            towards neutral (0), pixels per radian: a silhouette hardly shows a limb turning
            about itself, and a twist left free drifts frame after frame (0 turns it off).
        velocity_damping: the prediction is ``x_{t-1} + velocity_damping (x_{t-1} - x_{t-2})``
            (1: constant velocity, 0: the last pose).
        min_diag: floor of the solver's scaling (:attr:`torchfit.solver.LMOptions.min_diag`).
        jacobian: ``batched`` (forward differences, all the perturbed rows in one model
            call: the fastest on the CPU) or a solver Jacobian (``forward``, ``numeric``).
    """

    iterations: int = 8
    rounds: int = 2
    temporal_translation: float = 100.0
    temporal_rotation: float = 5.0
    temporal_joints: float = 2.0
    samples_per_edge: int = 2
    recover_factor: float = 2.5
    recover_min_px: float = 4.0
    confidence_px: float = 6.0
    floor_weight: float = 30.0
    min_diag: float = 1e-6
    contour_stride: int = 3
    jacobian: str = "batched"
    velocity_damping: float = 0.0
    twist_weight: float = 20.0


class PoseLayout:
    """Where the pose lives in a parameter row, its bounds and its temporal weights."""

    def __init__(self, model: BodyModel, options: TrackOptions) -> None:
        q = model.num_dofs
        kw = {"dtype": model.dtype, "device": model.device}
        inf = torch.full((6,), float("inf"), **kw)
        self.num_params = 6 + q
        self.floor_weight = options.floor_weight
        twist = torch.tensor([n.endswith(("twisting", "torsion")) for n in model.dof_names])
        #: (Q,) pull of each joint angle towards neutral, or None
        self.neutral = (options.twist_weight * twist).to(**kw) if options.twist_weight else None
        self.lower = torch.cat([-inf, model.joint_lower.to(**kw)])
        self.upper = torch.cat([inf, model.joint_upper.to(**kw)])
        self.weights = torch.cat(
            [
                torch.full((3,), options.temporal_translation, **kw),
                torch.full((3,), options.temporal_rotation, **kw),
                torch.full((q,), options.temporal_joints, **kw),
            ]
        )

    @staticmethod
    def split(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(translation, rotation, joint angles) of (B, P) rows."""
        return x[:, :3], x[:, 3:6], x[:, 6:]

    def clip(self, x: torch.Tensor) -> torch.Tensor:
        """``x`` inside the bounds."""
        return torch.maximum(torch.minimum(x, self.upper), self.lower)


@dataclass
class FrameResult:
    """One frame of B sequences.

    Attributes:
        x: (B, P) fitted pose rows.
        cost: (B,) final cost ``0.5 |r|²``.
        contour_rms: (B,) RMS of e_P (pixels): how far the person contour lies from the
            model's.
        iterations: (B,) LM iterations over all rounds.
    """

    x: torch.Tensor
    cost: torch.Tensor
    contour_rms: torch.Tensor
    iterations: torch.Tensor


def _pixels(model, scales, camera, x, vertex_index):
    t, r, q = PoseLayout.split(x)
    out = model(scales, q, t, r, vertex_index=vertex_index)
    return project_points(out.vertices, camera), out.vertices


class _FrameResidual:
    """The residuals of one frame for a fixed model-contour choice (rows by problem index)."""

    def __init__(self, model, scales, person, layout, prediction, sampler, selection):
        self.model, self.scales, self.layout = model, scales, layout
        self.camera = person.camera
        self.contours, self.valid = person.contours[0], person.valid[0]
        self.dist = person.distance_maps[0][:, None]
        self.prediction = prediction
        self.half = 0.5 / sampler.k
        ep = contour_endpoints(sampler, selection)
        marks = model.template.landmarks
        soles = [marks[k] for k in ("l_sole", "r_sole", "l_toe", "r_toe") if k in marks]
        self.floor_weight = layout.floor_weight if soles else 0.0
        extra = torch.tensor(soles, dtype=torch.long, device=ep.model_a.device)
        self.verts = torch.unique(torch.cat([ep.vertices(), extra]))
        self.soles = torch.searchsorted(self.verts, extra)
        where = lambda idx: torch.searchsorted(self.verts, idx)  # noqa: E731
        self.ma, self.mb = where(ep.model_a), where(ep.model_b)
        self.pa, self.pb = where(ep.person_a), where(ep.person_b)
        self.mt, self.pt = ep.model_t, ep.person_t
        self.sample_valid = selection.sample_valid
        self.n_model = selection.sample_valid.sum(1).clamp_min(1)
        self.n_person = self.valid.sum(1).clamp_min(1)

    def __call__(self, xr: torch.Tensor, index: torch.Tensor):
        p, world = _pixels(self.model, self.scales[index], self.camera[index], xr, self.verts)
        g = lambda t, i: torch.gather(t, 1, i[..., None].expand(-1, -1, 2))  # noqa: E731
        t = self.mt[index][..., None].to(xr.dtype)
        points = g(p, self.ma[index]) * (1 - t) + g(p, self.mb[index]) * t
        d_m = sample_distance_map(self.dist, points, rows=index)
        valid_m = self.sample_valid[index]
        e_m = torch.where(valid_m, d_m, torch.zeros_like(d_m))
        e_m = e_m / self.n_model[index, None].to(xr.dtype).sqrt()
        d_p = point_to_edge_distance(
            self.contours[index],
            g(p, self.pa[index]),
            g(p, self.pb[index]),
            self.pt[index],
            self.half,
        )
        valid_p = self.valid[index]
        e_p = torch.where(valid_p, d_p, torch.zeros_like(d_p))
        e_p = e_p / self.n_person[index, None].to(xr.dtype).sqrt()
        e_t = self.layout.weights * (xr - self.prediction[index])
        # floor: the lowest sole point on the floor (z = 0), soft
        z = world[:, self.soles, 2] if len(self.soles) else xr[:, :1] * 0
        e_f = self.floor_weight * z.min(1, keepdim=True).values
        parts = [e_p, e_m, e_t, e_f]
        if self.layout.neutral is not None:
            parts.append(self.layout.neutral * xr[:, 6:])
        mask = torch.cat(
            [valid_p, valid_m] + [torch.ones_like(e, dtype=torch.bool) for e in parts[2:]], 1
        )
        return torch.cat(parts, 1), mask

    def jacobian(self, xr: torch.Tensor, index: torch.Tensor):
        """Forward differences, every perturbed copy of the rows in one batched call."""
        n, p = xr.shape
        h = _STEP * torch.clamp(xr.abs(), min=1.0)
        eye = torch.eye(p, dtype=xr.dtype, device=xr.device)
        pert = (xr[None] + eye[:, None, :] * h[None]).reshape(p * n, p)
        with torch.no_grad():
            r0, _ = self(xr, index)
            rp, _ = self(pert, index.repeat(p))
        jac = (rp.reshape(p, n, -1) - r0[None]) / h.T[:, :, None]
        return jac.permute(1, 2, 0), r0

    def contour_rms(self, x: torch.Tensor) -> torch.Tensor:
        """(B,) RMS of e_P in pixels."""
        with torch.no_grad():
            r, _ = self(x, torch.arange(x.shape[0], device=x.device))
        e_p = r[:, : self.contours.shape[1]]
        return (e_p * e_p).sum(1).sqrt()  # e_P already carries 1 / sqrt(|C_P|)


def solve_frame(
    model: BodyModel,
    scales: torch.Tensor,
    person: PersonData,
    layout: PoseLayout,
    x0: torch.Tensor,
    prediction: torch.Tensor,
    options: TrackOptions,
    sampler: EdgeSampler | None = None,
) -> FrameResult:
    """Fit the pose of one frame of each of B sequences.

    Args:
        model: the body model.
        scales: (B, S, 3) the fitted segment scales of each sequence's subject.
        person: the frame's person data (J = 1 silhouette per row).
        layout: the pose layout.
        x0: (B, P) start.
        prediction: (B, P) the temporal term's target.
        options: tracker options.
        sampler: edge sampler of the model mesh (made when None).
    """
    sampler = sampler or EdgeSampler(model.faces, options.samples_per_edge)
    camera: Camera = person.camera
    x = layout.clip(x0)
    iterations = torch.zeros(x.shape[0], dtype=torch.long)
    lm = LMOptions(max_iter=options.iterations, fold_batch=False, min_diag=options.min_diag)
    cost = torch.zeros(x.shape[0], dtype=x.dtype)
    problem = None
    for _ in range(options.rounds):
        with torch.no_grad():
            pix, _ = _pixels(model, scales, camera, x, None)
        sel = select_contour(
            sampler, pix, person.contours[0], person.valid[0], camera.image_size, 1.0
        )
        problem = _FrameResidual(model, scales, person, layout, prediction, sampler, sel)
        res = levenberg_marquardt(
            problem,
            x,
            lm,
            jacobian=problem.jacobian if options.jacobian == "batched" else options.jacobian,
            lower=layout.lower,
            upper=layout.upper,
            indexed=True,
        )
        x, cost = res.x, res.cost
        iterations += res.n_iter.cpu().long()
    return FrameResult(x=x, cost=cost, contour_rms=problem.contour_rms(x), iterations=iterations)
