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
solves. The Jacobian is in closed form (:meth:`_FrameResidual.analytic_jacobian`).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch

from torchfit.body.model import BodyModel
from torchfit.camera import Camera, camera_centre, project_points, project_with_jacobian
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

#: limb joint whose depth the ``temporal_depth`` term holds -> the joint its limb hangs from.
_DEPTH_JOINTS = {
    f"{s}_{j}": f"{s}_{base}"
    for s in ("l", "r")
    for j, base in (("elbow", "shoulder"), ("wrist", "shoulder"), ("knee", "hip"), ("ankle", "hip"))
}


@dataclass(frozen=True)
class TrackOptions:
    """Options of the tracker.

    Attributes:
        iterations: LM iterations per contour choice.
        rounds: contour choices (each followed by an LM solve) per frame.
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
        ftol, xtol: the solver's stopping tolerances (:class:`torchfit.solver.LMOptions`):
            a row stops before ``iterations`` once its relative cost reduction or its
            relative step falls below them.
        min_diag: floor of the solver's scaling (:attr:`torchfit.solver.LMOptions.min_diag`).
        jacobian: ``analytic`` (the pose derivatives in closed form, one model call per
            Jacobian: the fastest), ``batched`` (forward differences, all the perturbed rows in
            one model call) or a solver Jacobian (``forward``, ``numeric``).
    """

    iterations: int = 8
    rounds: int = 2
    temporal_translation: float = 20.0
    start_translation: float = 100.0
    temporal_rotation: float = 5.0
    temporal_joints: float = 2.0
    samples_per_edge: int = 2
    recover_factor: float = 2.5
    recover_min_px: float = 4.0
    confidence_px: float = 6.0
    floor_weight: float = 30.0
    min_diag: float = 1e-6
    contour_stride: int = 3
    distance_margin_px: int | None = 48
    jacobian: str = "analytic"
    ftol: float = 1e-3
    xtol: float = 1e-3
    velocity_damping: float = 0.0
    twist_weight: float = 20.0
    temporal_depth: float = 15.0


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


def _limbs(layout: PoseLayout) -> torch.Tensor:
    """(2, K) the limb joints' vertices and those of the joints they hang from (K = 0 when
    the depth pull is off)."""
    limbs = layout.depth_vertices
    return limbs if layout.depth_weight else limbs[:, :0]


def _depth_target(model, scales, camera, prediction, layout):
    """Per row, each limb joint's camera ray (B, K, 3) and the prediction's offset of the
    joint from the one its limb hangs from, along that ray (B, K) (None, None without limbs).
    """
    limbs = _limbs(layout)
    if not limbs.shape[1]:
        return None, None
    t, r, q = PoseLayout.split(prediction)
    with torch.no_grad():
        world = model(scales, q, t, r, vertex_index=limbs.flatten()).vertices
    joint, base = world.reshape(world.shape[0], 2, -1, 3).unbind(1)
    centre = camera_centre(camera.R, camera.t).to(world)
    ray = joint - centre[:, None]
    rays = ray / ray.norm(dim=-1, keepdim=True)
    return rays, ((joint - base) * rays).sum(-1)


class _FrameResidual:
    """The residuals of one frame for a fixed model-contour choice (rows by problem index)."""

    def __init__(self, model, scales, person, layout, prediction, sampler, selection, target=None):
        self.model, self.scales, self.layout = model, scales, layout
        if target is None:  # the limbs' rays and depths (:func:`_depth_target`)
            target = _depth_target(model, scales, person.camera, prediction, layout)
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
        limbs = _limbs(layout).to(extra.device)
        self.verts = torch.unique(torch.cat([ep.vertices(), extra, limbs.flatten()]))
        self.soles = torch.searchsorted(self.verts, extra)
        self.limbs, self.bases = torch.searchsorted(self.verts, limbs)
        self.rays, self.depth = target
        where = lambda idx: torch.searchsorted(self.verts, idx)  # noqa: E731
        self.ma, self.mb = where(ep.model_a), where(ep.model_b)
        self.pa, self.pb = where(ep.person_a), where(ep.person_b)
        self.mt, self.pt = ep.model_t, ep.person_t
        self.sample_valid = selection.sample_valid
        self.n_model = selection.sample_valid.sum(1).clamp_min(1)
        self.n_person = self.valid.sum(1).clamp_min(1)
        self._last = None  # (rows, index, kinematics pass) of the last residual evaluation

    def _endpoints(self, p: torch.Tensor, index: torch.Tensor) -> dict[str, torch.Tensor]:
        """Each residual entry's own copy of its edge endpoints' pixels (N, n, 2)."""
        g = lambda t, i: torch.gather(t, 1, i[..., None].expand(-1, -1, t.shape[-1]))  # noqa: E731
        return {
            "pa": g(p, self.pa[index]),
            "pb": g(p, self.pb[index]),
            "ma": g(p, self.ma[index]),
            "mb": g(p, self.mb[index]),
        }

    def _contour_terms(
        self, ends: dict[str, torch.Tensor], index: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """e_P (N, C) and e_M (N, n_m) from the endpoint pixels (padding is zero)."""
        dtype = ends["pa"].dtype
        t = self.mt[index][..., None].to(dtype)
        points = ends["ma"] * (1 - t) + ends["mb"] * t
        d_m = sample_distance_map(self.dist, points, rows=index)
        e_m = torch.where(self.sample_valid[index], d_m, torch.zeros_like(d_m))
        e_m = e_m / self.n_model[index, None].to(dtype).sqrt()
        d_p = point_to_edge_distance(
            self.contours[index], ends["pa"], ends["pb"], self.pt[index], self.half
        )
        e_p = torch.where(self.valid[index], d_p, torch.zeros_like(d_p))
        e_p = e_p / self.n_person[index, None].to(dtype).sqrt()
        return e_p, e_m

    def _mask(self, index: torch.Tensor) -> torch.Tensor:
        valid_p, valid_m = self.valid[index], self.sample_valid[index]
        extra = 0 if self.layout.neutral is None else self.layout.num_params - 6
        extra += len(self.limbs)
        rest = torch.ones(valid_p.shape[0], self.layout.num_params + 1 + extra, dtype=torch.bool)
        return torch.cat([valid_p, valid_m, rest.to(valid_p.device)], 1)

    def _neutral(self, xr: torch.Tensor) -> list[torch.Tensor]:
        """The pull of the joint angles towards neutral (the twists), as a list of 0 or 1."""
        return [] if self.layout.neutral is None else [self.layout.neutral * xr[:, 6:]]

    def _limb_depth(self, xr: torch.Tensor, world: torch.Tensor, index: torch.Tensor):
        """The limb joints' depth pull (a list of 0 or 1 (N, K) terms)."""
        if not len(self.limbs):
            return []
        rel = world[:, self.limbs] - world[:, self.bases]
        return [self.layout.depth_weight * ((rel * self.rays[index]).sum(-1) - self.depth[index])]

    def _other_terms(
        self, xr: torch.Tensor, world: torch.Tensor, index: torch.Tensor
    ) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        """The terms beside the contour's: e_T towards the prediction, the floor (the lowest
        sole point on z = 0, soft) and the twists' pull; and, per row, the index in
        ``self.verts`` of the lowest sole point (None without soles)."""
        e_t = self.layout.weights * (xr - self.prediction[index])
        limbs = self._limb_depth(xr, world, index)
        if not len(self.soles):
            return [e_t, xr[:, :1] * 0, *self._neutral(xr), *limbs], None
        lowest = world[:, self.soles, 2].min(1, keepdim=True)
        e_f = self.floor_weight * lowest.values
        return [e_t, e_f, *self._neutral(xr), *limbs], self.soles[lowest.indices[:, 0]]

    def __call__(self, xr: torch.Tensor, index: torch.Tensor):
        t, r, q = PoseLayout.split(xr)
        passed = self.model.pose_pass(self.scales[index], q, t, r, self.verts)
        # the solver asks for the Jacobian where it accepts a step: the pass is kept for it
        self._last = (xr.clone(), index.clone(), passed)
        world = passed[2].vertices
        p = project_points(world, self.camera[index])
        e_p, e_m = self._contour_terms(self._endpoints(p, index), index)
        others, _ = self._other_terms(xr, world, index)
        return torch.cat([e_p, e_m, *others], 1), self._mask(index)

    def analytic_jacobian(self, xr: torch.Tensor, index: torch.Tensor):
        """The Jacobian in one pass: the posed contour vertices' pose derivatives in closed
        form (:meth:`BodyModel.pose_jacobian`), through the projection's derivative, times
        each residual entry's derivative w.r.t. its own endpoint pixels (reverse mode)."""
        n, p_count = xr.shape
        t, r, q = PoseLayout.split(xr)
        last, passed = self._last, None
        if last is not None and torch.equal(last[1], index) and torch.equal(last[0], xr):
            passed = last[2]  # the residual was evaluated here: its kinematics pass serves
        world, d_world = self.model.pose_jacobian(self.scales[index], q, t, r, self.verts, passed)
        pix, d_pix = project_with_jacobian(world, d_world, self.camera[index])
        ends = {k: v.detach().requires_grad_(True) for k, v in self._endpoints(pix, index).items()}
        with torch.enable_grad():
            e_p, e_m = self._contour_terms(ends, index)
            grads = torch.autograd.grad(
                e_p.sum() + e_m.sum(), list(ends.values()), allow_unused=True
            )
        local = {
            k: g if g is not None else torch.zeros_like(ends[k])
            for (k, g) in zip(ends, grads, strict=True)
        }

        # each residual entry's endpoint rows of d_pix, copied by row from the flattened batch
        flat = d_pix.reshape(-1, 2, p_count)
        first = torch.arange(n, device=xr.device)[:, None] * d_pix.shape[1]

        def chain(name: str, idx: torch.Tensor) -> torch.Tensor:
            tangents = flat.index_select(0, (idx + first).flatten()).view(*idx.shape, 2, p_count)
            g = local[name][..., None]
            return g[:, :, 0] * tangents[:, :, 0] + g[:, :, 1] * tangents[:, :, 1]

        j_p = chain("pa", self.pa[index]) + chain("pb", self.pb[index])
        j_m = chain("ma", self.ma[index]) + chain("mb", self.mb[index])
        j_t = torch.diag_embed(self.layout.weights.to(xr).expand(n, -1))
        others, low = self._other_terms(xr, world, index)
        if low is None:
            j_f = torch.zeros(n, 1, p_count, dtype=xr.dtype, device=xr.device)
        else:
            j_f = self.floor_weight * d_world[torch.arange(n), low, 2][:, None]
        r0 = torch.cat([e_p.detach(), e_m.detach(), *others], 1)
        jac = [j_p, j_m, j_t, j_f]
        if self.layout.neutral is not None:
            j_n = torch.zeros(n, p_count - 6, p_count, dtype=xr.dtype, device=xr.device)
            j_n[:, :, 6:] = torch.diag(self.layout.neutral.to(xr))
            jac.append(j_n)
        if len(self.limbs):
            d_rel = d_world[:, self.limbs] - d_world[:, self.bases]
            j_d = (self.rays[index][..., None] * d_rel).sum(2)
            jac.append(self.layout.depth_weight * j_d)
        return torch.cat(jac, 1), r0

    def batched_jacobian(self, xr: torch.Tensor, index: torch.Tensor):
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


_JACOBIANS = {
    "analytic": lambda problem: problem.analytic_jacobian,
    "batched": lambda problem: problem.batched_jacobian,
}


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
        layout: the pose layout (its bounds; the weights are taken from ``options``).
        x0: (B, P) start.
        prediction: (B, P) the temporal term's target.
        options: tracker options.
        sampler: edge sampler of the model mesh (made when None).
    """
    sampler = sampler or EdgeSampler(model.faces, options.samples_per_edge)
    layout = layout.for_options(options)  # the weights are this solve's (a restart's, ...)
    camera: Camera = person.camera
    x = layout.clip(x0)
    iterations = torch.zeros(x.shape[0], dtype=torch.long)
    lm = LMOptions(
        max_iter=options.iterations,
        fold_batch=False,
        min_diag=options.min_diag,
        ftol=options.ftol,
        xtol=options.xtol,
    )
    cost = torch.zeros(x.shape[0], dtype=x.dtype)
    target = _depth_target(model, scales, camera, prediction, layout)
    residual = None
    for _ in range(options.rounds):
        with torch.no_grad():
            pix, _ = _pixels(model, scales, camera, x, None)
        sel = select_contour(
            sampler, pix, person.contours[0], person.valid[0], camera.image_size, 1.0
        )
        problem = _FrameResidual(model, scales, person, layout, prediction, sampler, sel, target)
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
        )
        x, cost, residual = res.x, res.cost, res.residual
        iterations += res.n_iter.cpu().long()
    # the solver's last residual is the one at x: e_P leads it, already over sqrt(|C_P|)
    e_p = residual[:, : person.contours[0].shape[1]]
    rms = (e_p * e_p).sum(1).sqrt()
    return FrameResult(x=x, cost=cost, contour_rms=rms, iterations=iterations)
