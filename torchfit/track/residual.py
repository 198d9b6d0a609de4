"""The residuals of one tracked frame and their Jacobian in closed form (:class:`_FrameResidual`,
used by :func:`torchfit.track.frame.solve_frame`; the terms are described there)."""

from __future__ import annotations

import torch

from torchfit.body.model import BodyOutput
from torchfit.camera import camera_centre, project_points, project_with_jacobian
from torchfit.fit.model_contour import contour_endpoints, point_to_edge_distance
from torchfit.image.distance import sample_distance_map
from torchfit.track.options import PoseLayout

_STEP = 1e-6


def _limbs(layout: PoseLayout) -> torch.Tensor:
    """(2, K) the limb joints' vertices and those of the joints they hang from (K = 0 when
    the depth pull is off)."""
    limbs = layout.depth_vertices
    return limbs if layout.depth_weight else limbs[:, :0]


def _depth_target(model, scales, camera, prediction, layout, posed=None):
    """Per row, each limb joint's camera ray (B, K, 3) and the prediction's offset of the
    joint from the one its limb hangs from, along that ray (B, K) (None, None without limbs).
    ``posed``: (B, V, 3) every template vertex posed at the prediction, where the caller has
    them (the same numbers as posing the limbs' vertices here)."""
    limbs = _limbs(layout)
    if not limbs.shape[1]:
        return None, None
    if posed is not None:
        world = posed[:, limbs.flatten()]
    else:
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

    def __init__(
        self, model, scales, person, layout, prediction, sampler, selection, target=None, scale=None
    ):
        self.model, self.scales, self.layout = model, scales, layout
        if scale is None:  # the image's pixels
            scale = torch.ones(scales.shape[0], dtype=scales.dtype, device=scales.device)
        self.scale = scale  # (B,) reference pixels per image pixel
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
        self._first = False  # the first residual is to be made with the Jacobian (start_from)
        self._ahead = None  # (rows, index, (J, r)): the Jacobian made with the first residual
        self._picked: dict[tuple, dict] = {}  # index -> the per-row data of those rows

    _PER_ROW = ("scales", "pa", "pb", "ma", "mb", "mt", "pt", "contours", "valid")
    _PER_ROW += ("sample_valid", "n_model", "n_person", "prediction", "rays", "depth", "scale")

    def _at(self, index: torch.Tensor) -> dict[str, torch.Tensor]:
        """The per-row data of the rows ``index``, taken once per index set."""
        key = tuple(index.tolist())
        if key not in self._picked:
            got = {k: getattr(self, k) for k in self._PER_ROW}
            got = {k: v if v is None else v[index] for k, v in got.items()}
            got["camera"] = self.camera[index]
            got["mask"] = self._mask(got)
            if len(self._picked) >= 4:  # a solve meets few index sets; keep the latest
                del self._picked[next(iter(self._picked))]
            self._picked[key] = got
        return self._picked[key]

    def _endpoints(self, p: torch.Tensor, rows: dict) -> dict[str, torch.Tensor]:
        """Each residual entry's own copy of its edge endpoints' pixels (N, n, 2)."""
        g = lambda i: torch.gather(p, 1, i[..., None].expand(-1, -1, p.shape[-1]))  # noqa: E731
        return {k: g(rows[k]) for k in ("pa", "pb", "ma", "mb")}

    def _contour_terms(
        self, ends: dict[str, torch.Tensor], index: torch.Tensor, rows: dict
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """e_P (N, C) and e_M (N, n_m) from the endpoint pixels (padding is zero), in reference
        pixels (each row's ``scale``)."""
        dtype = ends["pa"].dtype
        scale = rows["scale"][:, None].to(dtype)
        t = rows["mt"][..., None].to(dtype)
        points = ends["ma"] * (1 - t) + ends["mb"] * t
        d_m = sample_distance_map(self.dist, points, rows=index)
        e_m = torch.where(rows["sample_valid"], d_m, torch.zeros_like(d_m))
        e_m = e_m * scale / rows["n_model"][:, None].to(dtype).sqrt()
        d_p = point_to_edge_distance(
            rows["contours"], ends["pa"], ends["pb"], rows["pt"], self.half
        )
        e_p = torch.where(rows["valid"], d_p, torch.zeros_like(d_p))
        e_p = e_p * scale / rows["n_person"][:, None].to(dtype).sqrt()
        return e_p, e_m

    def _mask(self, rows: dict) -> torch.Tensor:
        valid_p, valid_m = rows["valid"], rows["sample_valid"]
        extra = 0 if self.layout.neutral is None else self.layout.num_params - 6
        extra += len(self.limbs)
        rest = torch.ones(valid_p.shape[0], self.layout.num_params + 1 + extra, dtype=torch.bool)
        return torch.cat([valid_p, valid_m, rest.to(valid_p.device)], 1)

    def _neutral(self, xr: torch.Tensor) -> list[torch.Tensor]:
        """The pull of the joint angles towards neutral (the twists), as a list of 0 or 1."""
        return [] if self.layout.neutral is None else [self.layout.neutral * xr[:, 6:]]

    def _limb_depth(self, xr: torch.Tensor, world: torch.Tensor, rows: dict):
        """The limb joints' depth pull (a list of 0 or 1 (N, K) terms)."""
        if not len(self.limbs):
            return []
        rel = world[:, self.limbs] - world[:, self.bases]
        return [self.layout.depth_weight * ((rel * rows["rays"]).sum(-1) - rows["depth"])]

    def _other_terms(
        self, xr: torch.Tensor, world: torch.Tensor, rows: dict
    ) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        """The terms beside the contour's: e_T towards the prediction, the floor (the lowest
        sole point on z = 0, soft) and the twists' pull; and, per row, the index in
        ``self.verts`` of the lowest sole point (None without soles)."""
        e_t = self.layout.weights * (xr - rows["prediction"])
        limbs = self._limb_depth(xr, world, rows)
        if not len(self.soles):
            return [e_t, xr[:, :1] * 0, *self._neutral(xr), *limbs], None
        lowest = world[:, self.soles, 2].min(1, keepdim=True)
        e_f = self.floor_weight * lowest.values
        return [e_t, e_f, *self._neutral(xr), *limbs], self.soles[lowest.indices[:, 0]]

    def start_from(
        self, xr: torch.Tensor, index: torch.Tensor, whole: tuple, jacobian: bool = False
    ) -> None:
        """Hand over the kinematics pass ``whole`` of every template vertex at the rows
        ``xr`` (problems ``index``), made for the contour choice: the first residual there and
        the Jacobian take their vertices from it instead of posing the body again. With
        ``jacobian`` (the solve's is :meth:`analytic_jacobian`), the first residual there is
        the one the Jacobian makes with it (the same numbers), made once for the two."""
        rot_root, frames, out, seg = whole
        sub = BodyOutput(out.vertices[:, self.verts], out.origins, out.rotations)
        self._last = (xr.clone(), index.clone(), (rot_root, frames, sub, seg[self.verts]))
        self._first, self._ahead = jacobian, None

    def pass_at(self, xr: torch.Tensor, vertex_index: torch.Tensor) -> tuple | None:
        """A kinematics pass of the template vertices ``vertex_index`` at the rows ``xr`` of
        every problem in order, from the last one made there (the solver's accepted trial
        point: a frame's next contour choice starts where its last solve ended), or None."""
        if not self._at_last(xr, torch.arange(xr.shape[0], device=xr.device)):
            return None
        return self.model.repose(self._last[2], self.scales, vertex_index)

    def _at_last(self, xr: torch.Tensor, index: torch.Tensor) -> bool:
        """Whether the last kinematics pass was made at the rows ``xr`` of problems ``index``."""
        last = self._last
        return last is not None and torch.equal(last[1], index) and torch.equal(last[0], xr)

    def _pass(self, xr: torch.Tensor, index: torch.Tensor, rows: dict) -> tuple:
        """The kinematics pass at ``xr``: the one handed over or last made there, else new."""
        if self._at_last(xr, index):
            return self._last[2]
        t, r, q = PoseLayout.split(xr)
        return self.model.pose_pass(rows["scales"], q, t, r, self.verts)

    def __call__(self, xr: torch.Tensor, index: torch.Tensor):
        if self._first and self._at_last(xr, index):
            self._first = False
            made = self.analytic_jacobian(xr, index)
            self._ahead = (xr.clone(), index.clone(), made)
            return made[1], self._at(index)["mask"]
        rows = self._at(index)
        passed = self._pass(xr, index, rows)
        # the solver asks for the Jacobian where it accepts a step: the pass is kept for it
        self._last = (xr.clone(), index.clone(), passed)
        world = passed[2].vertices
        p = project_points(world, rows["camera"])
        e_p, e_m = self._contour_terms(self._endpoints(p, rows), index, rows)
        others, _ = self._other_terms(xr, world, rows)
        return torch.cat([e_p, e_m, *others], 1), rows["mask"]

    def analytic_jacobian(self, xr: torch.Tensor, index: torch.Tensor):
        """The Jacobian in one pass: the posed contour vertices' pose derivatives in closed
        form (:meth:`BodyModel.pose_jacobian`), through the projection's derivative, times
        each residual entry's derivative w.r.t. its own endpoint pixels (reverse mode)."""
        ahead, self._ahead = self._ahead, None
        if ahead and torch.equal(ahead[1], index) and torch.equal(ahead[0], xr):
            return ahead[2]  # made with the first residual, here
        n, p_count = xr.shape
        t, r, q = PoseLayout.split(xr)
        rows = self._at(index)
        passed = self._pass(xr, index, rows)  # the residual's, where it was evaluated here
        world, d_world = self.model.pose_jacobian(rows["scales"], q, t, r, self.verts, passed)
        pix, d_pix = project_with_jacobian(world, d_world, rows["camera"])
        ends = {k: v.detach().requires_grad_(True) for k, v in self._endpoints(pix, rows).items()}
        with torch.enable_grad():
            e_p, e_m = self._contour_terms(ends, index, rows)
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

        j_p = chain("pa", rows["pa"]) + chain("pb", rows["pb"])
        j_m = chain("ma", rows["ma"]) + chain("mb", rows["mb"])
        j_t = torch.diag_embed(self.layout.weights.to(xr).expand(n, -1))
        others, low = self._other_terms(xr, world, rows)
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
            j_d = (rows["rays"][..., None] * d_rel).sum(2)
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
