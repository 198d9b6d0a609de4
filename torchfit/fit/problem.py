"""The six-posture silhouette fit (first paper, sections 6–8; design.md section 6), batched.

:class:`SilhouetteFit` is the problem for B subjects: residuals (e_P per person contour pixel
and e_M per posture, then e_B per parameter; :mod:`torchfit.fit.layout` owns where each lives)
and their Jacobian.

The Jacobian is computed with the discrete contour choice made once per evaluation point. Per
posture, the contour vertices' pixel derivatives w.r.t. the parameters that posture depends on
(the scales and its own parameters) are in closed form (:meth:`torchfit.fit.pose.Poser.
world_jacobian` through :func:`torchfit.camera.project_with_jacobian`), and reverse mode gives
the derivative of every residual entry w.r.t. the pixels of its own edge endpoints; their
product is the posture's block.
"""

from __future__ import annotations

import torch

from torchfit.body.model import BodyModel
from torchfit.camera import camera_centre, project_points
from torchfit.errors import ConfigError
from torchfit.fit.jacobian import ENDPOINTS, jacobian_and_residual
from torchfit.fit.layout import JointBounds
from torchfit.fit.model_contour import (
    ContourEndpoints,
    ContourSelection,
    EdgeSampler,
    contour_endpoints,
    point_to_edge_distance,
    select_contours,
)
from torchfit.fit.options import FitOptions, image_scale
from torchfit.fit.person import PersonData
from torchfit.fit.pose import Poser, template_layout
from torchfit.fit.residuals import barrier, model_to_person, person_to_model
from torchfit.image.distance import sample_distance_map

# FitOptions lives in torchfit.fit.options; importable from here as before
__all__ = ["FitOptions", "SilhouetteFit"]


class SilhouetteFit:
    """The fitting problem for a batch of subjects: residuals and their Jacobian.

    Args:
        model: the body model (its dtype and device are used).
        person: the person data of B subjects.
        options: postures, free joints, bounds, contour sampling.
        scale_bounds: (min, max) of every segment scale.
    """

    def __init__(
        self,
        model: BodyModel,
        person: PersonData,
        options: FitOptions | None = None,
        scale_bounds: tuple[float, float] = (0.4, 1.9),
    ) -> None:
        self.model = model
        self.person = person
        self.options = options = options or FitOptions()
        self.scale_bounds = scale_bounds
        kw = {"dtype": model.dtype, "device": model.device}
        self.kw = kw
        self.batch = person.batch_size
        self.camera = person.camera.to(device=model.device, dtype=model.dtype)
        self.poses = list(options.poses)
        self.sampler = EdgeSampler(model.faces, options.samples_per_edge)
        layout = template_layout(
            model,
            self.poses,
            options.free_joints,
            scale_bounds,
            JointBounds(
                options.translation_max_m,
                options.yaw_max_deg,
                options.tilt_max_deg,
                options.side_roll_max_deg,
            ),
        )
        self.layout = layout
        self.residual_layout = layout.residual_layout(person.contour_lengths)
        self.poser = Poser(model, layout, camera_centre(self.camera.R, self.camera.t))
        self.lower = layout.lower(**kw)
        self.upper = layout.upper(**kw)
        #: (B, J) weight of each posture's residuals (e_P and e_M), 1 unless down-weighted.
        self.pose_weights = torch.ones(self.batch, len(self.poses), **kw)
        #: (B,) reference pixels per image pixel (``options.reference_px_per_m``; 1 without)
        self.image_scale = image_scale(
            self.camera, options.reference_px_per_m, options.pixel_noise_ratio
        ).to(**kw)
        #: (parameters, rows, choice) of the last :meth:`select`
        self._last_choice: tuple | None = None

    def subset(self, index: list[int]) -> SilhouetteFit:
        """The same problem for a subset of the subjects (same layout and residual width)."""
        out = type(self)(**self._arguments(index))
        out.pose_weights = self.pose_weights[index].clone()
        return out

    def _arguments(self, index: list[int]) -> dict:
        """The constructor's arguments for the subjects ``index`` (a subclass adds its own)."""
        return {
            "model": self.model,
            "person": self.person.subset(index),
            "options": self.options,
            "scale_bounds": self.scale_bounds,
        }

    # ------------------------------------------------------------------------------------
    @property
    def num_params(self) -> int:
        """P, the number of parameters per subject."""
        return self.layout.num_params

    def initial_params(self) -> torch.Tensor:
        """(B, P) the template start: unit scales, nominal angles, root on the mark."""
        return self.layout.initial(**self.kw).expand(self.batch, -1).clone()

    def stage_indices(self, scales: list[str], joints: bool, root: bool) -> torch.Tensor:
        """Indices of the parameters a stage frees (its scale groups, and every posture's
        joints and/or root)."""
        idx = self.layout.free_indices(list(scales), joints, root)
        if not idx:
            raise ConfigError(f"fit stage frees no parameter (scales={list(scales)})")
        return torch.tensor(idx, device=self.model.device)

    # ------------------------------------------------------------------------------------
    def pose_state(self, full: torch.Tensor, j: int, rows: torch.Tensor):
        """Scales, angles and root of pose j (see :meth:`torchfit.fit.pose.Poser.state`)."""
        return self.poser.state(full, j, rows)

    def pose_world(
        self,
        full: torch.Tensor,
        j: int,
        rows: torch.Tensor,
        vertex_index: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posed vertices (N, K, 3) and segment origins (N, S, 3) of pose j, standing on the
        floor (see :meth:`torchfit.fit.pose.Poser.world`)."""
        return self.poser.world(full, j, rows, vertex_index)

    def project(self, points: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """(N, K, 2) pixels of world points (N, K, 3) in each row's camera."""
        return project_points(points, self.camera[rows])

    def pose_pixels(
        self,
        full: torch.Tensor,
        j: int,
        rows: torch.Tensor,
        vertex_index: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Posed, floor-standing vertices of pose j projected into each row's camera.

        Args:
            full: (N, P) parameters.
            rows: (N,) subject index of each row.
            vertex_index: optional (K,) template vertices to project (default: all).

        Returns:
            (N, K, 2) pixels.
        """
        return self.project(self.pose_world(full, j, rows, vertex_index)[0], rows)

    @torch.no_grad()
    def select(
        self, full: torch.Tensor, rows: torch.Tensor | None = None
    ) -> dict[int, ContourSelection]:
        """The discrete model-contour choice at ``full`` (N, P), one per pose.

        The last choice is kept: asked again at the same parameters and rows (the posture
        check, the judge and the outputs all read the final one), it is returned as it is, not
        made again. Callers do not modify it.

        Args:
            full: (N, P) parameters.
            rows: (N,) subject of each row (default: row i is subject i).
        """
        if rows is None:
            rows = torch.arange(full.shape[0], device=full.device)
        last = self._last_choice
        if last is not None and torch.equal(last[0], full) and torch.equal(last[1], rows):
            return last[2]
        chosen = self._choose(full, rows)
        self._last_choice = (full.clone(), rows.clone(), chosen)
        return chosen

    def _choose(self, full: torch.Tensor, rows: torch.Tensor) -> dict[int, ContourSelection]:
        """:meth:`select`'s choice, made (a subclass adds to it)."""
        posed = self.poser.world_postures(full, list(self.poses), rows)
        normals = self.person.normals
        chosen = select_contours(
            self.sampler,
            [self.project(posed[k], rows) for k in range(len(self.poses))],
            [self.person.contours[k][rows] for k in range(len(self.poses))],
            [self.person.valid[k][rows] for k in range(len(self.poses))],
            self.camera.image_size,
            self.options.contour_tolerance_px,
            None if normals is None else [n[rows] for n in normals],
            # in reference pixels (FitOptions.reference_px_per_m), as a limb's width
            [self.options.contour_orientation_px / self.image_scale[rows]] * len(self.poses),
        )
        return dict(zip(self.poses, chosen, strict=True))

    def _sample_rows(self, k: int, rows: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """Bilinear D_P of pose index k for each row's subject at (N, n, 2) points."""
        dmap = self.person.distance_maps[k]  # (B, H, W), read in the points' dtype
        return sample_distance_map(dmap.unsqueeze(1), points, rows)

    def _terms(
        self, k: int, rows: torch.Tensor, ends: ContourEndpoints, pix: dict[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """e_P (N, C) and the model contour points (N, N_m, 2) from endpoint pixels ``pix``."""
        contour = self.person.contours[k][rows].to(pix["pa"])
        valid = self.person.valid[k][rows]
        dist = point_to_edge_distance(
            contour, pix["pa"], pix["pb"], ends.person_t.to(contour), 0.5 / self.sampler.k
        )
        t = ends.model_t.to(contour)[..., None]
        points = pix["ma"] * (1 - t) + pix["mb"] * t
        return person_to_model(dist, valid), points

    def _endpoint_pixels(
        self, pixels: torch.Tensor, lookup: torch.Tensor, ends: ContourEndpoints
    ) -> dict[str, torch.Tensor]:
        r = torch.arange(pixels.shape[0], device=pixels.device)[:, None]
        return {n: pixels[r, lookup[getattr(ends, a)]] for n, a in ENDPOINTS.items()}

    def _prepare(
        self, sel: ContourSelection
    ) -> tuple[ContourEndpoints, torch.Tensor, torch.Tensor]:
        ends = contour_endpoints(self.sampler, sel)
        vidx = ends.vertices()
        lookup = torch.zeros(
            self.model.template.vertices.shape[0], dtype=torch.long, device=vidx.device
        )
        lookup[vidx] = torch.arange(vidx.numel(), device=vidx.device)
        return ends, vidx, lookup

    def _pose_terms(
        self,
        k: int,
        rows: torch.Tensor,
        ends: ContourEndpoints,
        sel: ContourSelection,
        pix: dict[str, torch.Tensor],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        e_p, points = self._terms(k, rows, ends, pix)
        valid = sel.sample_valid
        if self.person.uncertain is not None:
            valid = valid & ~self._uncertain_at(k, rows, points)
        e_m = model_to_person(self._sample_rows(k, rows, points), valid)
        return e_p, e_m

    def _uncertain_at(self, k: int, rows: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """(N, n) bool: the uncertain flag of pose index k at the pixel nearest each point (a
        choice, like the contour's, made at each evaluation point)."""
        flags = self.person.uncertain[k].to(points.device)  # (B, H, W)
        h, w = flags.shape[-2:]
        p = points.detach()
        u = p[..., 0].round().clamp(0, w - 1).long()
        v = p[..., 1].round().clamp(0, h - 1).long()
        return flags[rows[:, None].expand_as(u), v, u]

    def pose_residual(
        self, full: torch.Tensor, j: int, rows: torch.Tensor, selection: ContourSelection
    ) -> torch.Tensor:
        """[e_P (C_j entries), e_M] of pose j for rows ``full`` (N, P) -> (N, C_j + 1)."""
        prepared = self._prepare(selection)
        pixels = self.pose_pixels(full, j, rows, prepared[1])
        return self._image_part(self.poses.index(j), rows, selection, prepared, pixels)

    def _image_part(
        self,
        k: int,
        rows: torch.Tensor,
        selection: ContourSelection,
        prepared: tuple[ContourEndpoints, torch.Tensor, torch.Tensor],
        pixels: torch.Tensor,
    ) -> torch.Tensor:
        """[e_P, e_M] of pose index k from the (N, K, 2) pixels of its contour vertices."""
        ends, _, lookup = prepared
        pix = self._endpoint_pixels(pixels, lookup, ends)
        e_p, e_m = self._pose_terms(k, rows, ends, selection, pix)
        return torch.cat([e_p, e_m[:, None]], dim=1) * self.image_weights(rows, k)

    def _postures_pixels(
        self, full: torch.Tensor, rows: torch.Tensor, vertex_index: list[torch.Tensor]
    ) -> list[torch.Tensor]:
        """Per posture, the (N, K_k, 2) pixels of its ``vertex_index[k]`` (as
        :meth:`pose_pixels` gives them), from one model call and one projection over all the
        postures' rows and the union of their vertices."""
        union = torch.unique(torch.cat(vertex_index))
        posed = self.poser.world_postures(full, list(self.poses), rows, union)
        n = len(self.poses)
        pixels = self.project(torch.cat(posed), rows.repeat(n)).split(full.shape[0])
        return [
            p[:, torch.searchsorted(union, v)] for p, v in zip(pixels, vertex_index, strict=True)
        ]

    def image_weights(self, rows: torch.Tensor, k: int) -> torch.Tensor:
        """(N, 1) the factor of pose index k's image residuals in rows ``rows``: its posture
        weight times the subject's :attr:`image_scale`."""
        return (self.pose_weights[rows, k] * self.image_scale[rows])[:, None]

    def loss_units(self) -> torch.Tensor:
        """(B, M) size of one (reference) pixel in each residual entry, for the solver's robust
        loss.

        An e_P entry is a distance in reference pixels (:attr:`image_scale` times the image's)
        divided by ``sqrt(|C_P|)`` and times its posture's weight; e_M and e_B stay least
        squares (``inf``).
        """
        parts = []
        for k, valid in enumerate(self.person.valid):
            count = valid.sum(dim=1, keepdim=True).clamp_min(1).to(self.pose_weights)
            unit = (self.pose_weights[:, k, None] / count.sqrt()).expand(-1, valid.shape[1])
            inf = torch.full((self.batch, 1), torch.inf, **self.kw)
            parts.append(torch.cat([unit, inf], 1))
        parts.append(torch.full((self.batch, self.num_params), torch.inf, **self.kw))
        return torch.cat(parts, 1)

    def residual_mask(self) -> torch.Tensor:
        """(B, M) validity of the residual entries (padding of e_P is False)."""
        device = self.person.valid[0].device
        parts = [
            torch.cat([v, torch.ones(self.batch, 1, dtype=torch.bool, device=v.device)], 1)
            for v in self.person.valid
        ]
        parts.append(torch.ones(self.batch, self.num_params, dtype=torch.bool, device=device))
        return torch.cat(parts, 1)

    def barrier_residual(self, full: torch.Tensor) -> torch.Tensor:
        """(B, P) e_B of parameter rows ``full``."""
        return barrier(full, self.lower, self.upper, self.options.barrier_weight)

    def residual(
        self,
        full: torch.Tensor,
        selections: dict[int, ContourSelection] | None = None,
        rows: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """(N, M) residuals at ``full`` (N, P); the contour choice is made here if not given.

        Args:
            full: (N, P) parameters.
            selections: the contour choice of each row (as :meth:`select` makes it).
            rows: (N,) subject of each row (default: row i is subject i).
        """
        if rows is None:
            rows = torch.arange(full.shape[0], device=full.device)
        selections = selections or self.select(full, rows)
        prepared = [self._prepare(selections[j]) for j in self.poses]
        pixels = self._postures_pixels(full, rows, [p[1] for p in prepared])
        parts = [
            self._image_part(k, rows, selections[j], prepared[k], pixels[k])
            for k, j in enumerate(self.poses)
        ]
        parts.append(self.barrier_residual(full))
        return torch.cat(parts, 1)

    def jacobian_blocks(self, free: torch.Tensor) -> list[tuple[slice, torch.Tensor]]:
        """The Jacobian's sparsity w.r.t. the ``free`` (F,) parameters (for the solver's
        normal equations): posture j's e_P and e_M entries depend on the scales and on its
        own parameters only (positions in ``free``); the barrier rows are left dense."""
        rl = self.residual_layout
        scale = (free < self.layout.num_scale_params).nonzero().flatten()
        out = []
        for j in self.poses:
            sl = self.layout.blocks[j].columns
            own = ((free >= sl.start) & (free < sl.stop)).nonzero().flatten()
            out.append((rl.block(j), torch.cat([scale, own])))
        return out

    # ------------------------------------------------------------------------------------
    def jacobian(
        self,
        full: torch.Tensor,
        free: torch.Tensor,
        selections: dict[int, ContourSelection],
        rows: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """(N, M, F) Jacobian of :meth:`residual` w.r.t. the ``free`` (F,) parameters (see
        :meth:`jacobian_and_residual`)."""
        return self.jacobian_and_residual(full, free, selections, rows)[0]

    def jacobian_and_residual(
        self,
        full: torch.Tensor,
        free: torch.Tensor,
        selections: dict[int, ContourSelection],
        rows: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The (N, M, F) Jacobian of :meth:`residual` w.r.t. the ``free`` (F,) parameters, and
        the (N, M) residual itself (bit for bit :meth:`residual`'s, from the same pass).

        ``full`` (N, P) are parameter rows of the subjects ``rows`` (N,) (default: row i is
        subject i), ``selections`` their contour choice.

        Per pose, two derivatives meet at the projected contour vertices:

        - the pixel derivatives of the vertices that carry contour samples w.r.t. the
          parameters this pose depends on (the scales and its own parameters), in closed form
          (:meth:`torchfit.fit.pose.Poser.world_jacobian`, then the projection's);
        - reverse mode gives the derivative of every residual entry w.r.t. the pixels of its
          own edge endpoints (each e_P entry depends on one edge, e_M on the sample edges).

        Their product is the Jacobian block.
        """
        return jacobian_and_residual(self, full, free, selections, rows)
