"""Bent joints marked on the person's limbs: the flexed knee of posture 3 placed by its limbs.

The contour terms place a bent joint only as well as the rigid template's flesh at the bend
matches the person's: in posture 3 the fitted knee sat about 5 px (2 cm) below the true one
on the development sets, and the leg's split between thigh and shank followed the template's
instead of the person's (``benchmarks/RESULTS.md``, "The knee from its limbs").

The limbs on either side of a bent joint are straight bands on the silhouette, and the axes of
the two bands cross near the joint (:func:`torchfit.image.bends.crossing`). Not at the joint
centre itself: a calf bulges behind the shank's bone. The model, drawn at its current pose,
shows the same crossing on its own silhouette, so the person's joint is where the model's
joint would be moved by the difference of the two crossings:

    target = π(joint) + bend(person silhouette) − bend(model silhouette)

with both crossings taken along the model's own projected joints. The target is made with
each contour choice (and like it, outside the derivatives), and the fit adds

    e_J = weight * (π(joint) − target)

two entries (u, v) per marked joint, in pixels times ``weight``; a joint whose crossing is not
found on either silhouette, or moves more than ``max_shift_px``, has e_J = 0 until the next
choice. Pixels ``(u, v)``, ``v`` down, as :mod:`torchfit.image.contours`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.autograd.forward_ad as fwad

from torchfit.body.model import BodyModel
from torchfit.camera import project_with_jacobian
from torchfit.errors import ConfigError, DataError
from torchfit.fit.model_contour import ContourSelection
from torchfit.fit.person import PersonData
from torchfit.fit.prior import KnownFacts, PriorFit, PriorOptions, ScalePrior
from torchfit.fit.problem import FitOptions
from torchfit.image.bends import crossing

__all__ = ["BendOptions", "Bend", "SHOWN_BY", "parse_bends", "bend_target", "BendFit"]

#: The measurements a marked joint's place shows (by the joint's name without its side).
SHOWN_BY: dict[str, tuple[str, ...]] = {
    "knee": ("thigh_m", "lower_leg_m"),
    "elbow": ("upper_arm_m", "forearm_m"),
}


@dataclass(frozen=True)
class BendOptions:
    """The bent-joint marks of the fit.

    Attributes:
        weight: the weight of e_J (0: no marks). One pixel of a joint's offset from its
            target costs ``weight²``, as a posture whose contour is ``weight`` pixels off on
            average (e_M).
        joints: the marked joints, ``"pose<j>:<proximal>,<joint>,<distal>"`` with
            design.md's joint names: the joint, bent in posture j, between the limbs to its
            two neighbours.
        max_shift_px: a crossing that moves the joint further than this is not trusted
            (a silhouette that lost part of a limb). This, ``shown_px`` and e_J are in
            reference pixels (:class:`torchfit.fit.FitOptions` ``reference_px_per_m``).
        min_angle_deg: the smallest bend between the two limbs' axes that marks the joint.
        max_width_ratio: a person's limb band more than this many times wider or narrower
            than the model's (median widths of the sections that made the two axes) is not
            trusted: most of it lost to the segmentation, or merged with another limb.
        shown_px: a fitted joint within this of its mark shows the measurements it splits
            (:data:`SHOWN_BY`: the knee the thigh and the lower leg), and the judge takes
            their proportions from the images even outside the population's 1st–99th
            percentiles (``torchfit.pipeline.checks``).
    """

    weight: float = 0.0
    joints: tuple[str, ...] = ("pose3:l_hip,l_knee,l_ankle",)
    max_shift_px: float = 15.0
    min_angle_deg: float = 30.0
    max_width_ratio: float = 1.5
    shown_px: float = 2.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.weight) and self.weight >= 0):
            raise ConfigError(f"fit.bends.weight: expected a number >= 0, got {self.weight!r}")
        if not self.max_shift_px > 0:
            raise ConfigError(
                f"fit.bends.max_shift_px: expected a number > 0, got {self.max_shift_px!r}"
            )
        if not 0 < self.min_angle_deg < 90:
            raise ConfigError(
                f"fit.bends.min_angle_deg: expected a number in (0, 90), got {self.min_angle_deg!r}"
            )
        if not self.max_width_ratio > 1:
            raise ConfigError(
                f"fit.bends.max_width_ratio: expected a number > 1, got {self.max_width_ratio!r}"
            )
        if not self.shown_px >= 0:
            raise ConfigError(f"fit.bends.shown_px: expected a number >= 0, got {self.shown_px!r}")
        parse_bends(self.joints)


@dataclass(frozen=True)
class Bend:
    """One marked joint: ``joint``, bent in ``posture``, between ``proximal`` and ``distal``."""

    posture: int
    proximal: str
    joint: str
    distal: str

    @property
    def names(self) -> tuple[str, str, str]:
        """The three joints, proximal first."""
        return (self.proximal, self.joint, self.distal)


def parse_bends(specs: Sequence[str]) -> list[Bend]:
    """``["pose3:l_hip,l_knee,l_ankle", ...]`` -> :class:`Bend` list (ConfigError if
    malformed)."""
    out = []
    for spec in specs:
        pose, _, names = str(spec).partition(":")
        parts = [n.strip() for n in names.split(",")]
        number = pose.strip().removeprefix("pose")
        if not number.isdigit() or not 1 <= int(number) <= 6 or len(parts) != 3 or "" in parts:
            raise ConfigError(
                f"fit.bends.joints: expected 'pose<1-6>:<proximal>,<joint>,<distal>', got {spec!r}"
            )
        out.append(Bend(int(number), *parts))
    return out


def bend_target(
    person: np.ndarray,
    model: np.ndarray,
    joints: np.ndarray,
    max_shift_px: float,
    min_angle_deg: float,
    max_width_ratio: float,
) -> np.ndarray | None:
    """Where the person's joint is, from the two silhouettes' limb crossings.

    Args:
        person, model: (H, W) bool silhouettes of the person and of the model as it stands.
        joints: (3, 2) the model's projected proximal joint, joint and distal joint, pixels.
        max_shift_px, min_angle_deg, max_width_ratio: as :class:`BendOptions`.

    Returns:
        (2,) pixel target of the joint, or ``None`` where a crossing is not found, a
        person's limb band is not as wide as the model's within ``max_width_ratio``, or the
        shift exceeds ``max_shift_px``.
    """
    on_person = crossing(person, *joints, min_angle_deg=min_angle_deg)
    on_model = crossing(model, *joints, min_angle_deg=min_angle_deg)
    if on_person is None or on_model is None:
        return None
    for mine, theirs in ((on_person.upper, on_model.upper), (on_person.lower, on_model.lower)):
        ratio = mine.width / theirs.width
        if not 1 / max_width_ratio <= ratio <= max_width_ratio:
            return None
    shift = on_person.point - on_model.point
    if float(np.hypot(*shift)) > max_shift_px:
        return None
    return joints[1] + shift


class BendFit(PriorFit):
    """:class:`~torchfit.fit.prior.PriorFit` plus e_J, the bent-joint marks, after e_A.

    Args:
        model, person, options, scale_bounds, prior, prior_options, facts: as
            :class:`~torchfit.fit.prior.PriorFit`; ``person.silhouettes`` must hold the
            silhouettes of every posture with a marked joint.
        bends: the marks and their weight.
    """

    def __init__(
        self,
        model: BodyModel,
        person: PersonData,
        options: FitOptions | None = None,
        scale_bounds: tuple[float, float] = (0.4, 1.9),
        prior: ScalePrior | None = None,
        prior_options: PriorOptions | None = None,
        facts: Sequence[KnownFacts] | None = None,
        bends: BendOptions | None = None,
    ) -> None:
        super().__init__(model, person, options, scale_bounds, prior, prior_options, facts)
        self.bend_options = bends = bends or BendOptions()
        known = model.template.joints
        marks = [b for b in parse_bends(bends.joints) if b.posture in self.poses]
        for b in marks:
            unknown = [n for n in b.names if n not in known]
            if unknown:
                raise ConfigError(
                    f"fit.bends.joints: {unknown} not joints of template "
                    f"{model.template.name!r} (joints: {sorted(known)})"
                )
        #: posture -> its marks, in ``poses`` order (postures without one left out)
        self.marks = {
            j: [b for b in marks if b.posture == j]
            for j in self.poses
            if any(b.posture == j for b in marks)
        }
        for j in self.marks:
            silhouettes = person.silhouettes or {}
            if self.poses.index(j) not in silhouettes:
                raise DataError(f"bent-joint marks in pose{j} need the person's silhouettes")
        self._segments = {
            j: torch.tensor(
                [[known[n] for n in b.names] for b in m], dtype=torch.long, device=model.device
            )
            for j, m in self.marks.items()
        }
        #: the measurements the marks can show (:data:`SHOWN_BY`), found or not
        self.can_show = {
            key for m in self.marks.values() for b in m for key in SHOWN_BY.get(_kind(b.joint), ())
        }
        #: posture -> the parameter columns that can move its marked joints (those of the
        #: Jacobian's forward mode; the others' derivatives are structurally zero)
        self._moving = {j: self._moving_columns(j) for j in self.marks}
        rl = self.residual_layout
        self.residual_layout = self.layout.residual_layout(
            person.contour_lengths,
            rl.num_prior,
            rl.num_facts,
            rl.num_pose_prior,
            2 * sum(len(m) for m in self.marks.values()),
        )

    def _arguments(self, index: list[int]) -> dict:
        return {**super()._arguments(index), "bends": self.bend_options}

    # ------------------------------------------------------------------------------------
    def _mark_rows(self) -> dict[int, slice]:
        """posture -> its e_J columns."""
        out, at = {}, self.residual_layout.marks.start
        for j, m in self.marks.items():
            out[j] = slice(at, at + 2 * len(m))
            at += 2 * len(m)
        return out

    def joint_pixels(self, full: torch.Tensor, j: int, rows: torch.Tensor) -> torch.Tensor:
        """(N, L, 3, 2) pixels of the proximal joint, joint and distal joint of posture j's
        L marks, for parameter rows ``full`` (N, P) of the subjects ``rows``."""
        empty = torch.zeros(0, dtype=torch.long, device=full.device)
        origins = self.pose_world(full, j, rows, empty)[1]
        seg = self._segments[j]
        points = origins[:, seg.flatten()]  # (N, L*3, 3)
        return self.project(points, rows).reshape(full.shape[0], *seg.shape, 2)

    def _choose(self, full: torch.Tensor, rows: torch.Tensor) -> dict[int, ContourSelection]:
        """The contour choice (:meth:`SilhouetteFit.select`), with each marked posture's joint
        targets (``ContourSelection.marks``)."""
        chosen = super()._choose(full, rows)
        opts = self.bend_options
        for j, marks in self.marks.items():
            sel = chosen[j]
            joints = self.joint_pixels(full, j, rows).cpu().numpy()
            person = self.person.silhouettes[self.poses.index(j)]
            out = np.zeros((full.shape[0], len(marks), 3))
            for i, subject in enumerate(rows.tolist()):
                mask = person[subject].cpu().numpy()
                model = sel.mask(i) > 0
                # max_shift_px is in reference pixels (FitOptions.reference_px_per_m)
                shift = opts.max_shift_px / float(self.image_scale[subject])
                for m in range(len(marks)):
                    target = bend_target(
                        mask, model, joints[i, m], shift, opts.min_angle_deg, opts.max_width_ratio
                    )
                    if target is not None:
                        out[i, m] = (target[0], target[1], 1.0)
            sel.marks = torch.as_tensor(out, **self.kw)
        return chosen

    def _marks_at(self, sel: ContourSelection, n: int, count: int) -> torch.Tensor:
        if sel.marks is None:
            return torch.zeros(n, count, 3, **self.kw)
        return sel.marks

    def _entries(
        self, pixels: torch.Tensor, target: torch.Tensor, rows: torch.Tensor
    ) -> torch.Tensor:
        """(N, 2 L) e_J from the marked joints' pixels (N, L, 2) and their targets (N, L, 3)
        of subjects ``rows`` (N,), in reference pixels."""
        r = (pixels - target[..., :2]) * self._mark_weights(target, rows)
        return r.reshape(pixels.shape[0], -1)

    def _mark_weights(self, target: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """(N, L, 1): the weight of each mark's two entries (0 where it has no target), times
        the subject's :attr:`image_scale`."""
        return self.bend_options.weight * target[..., 2:] * self.image_scale[rows][:, None, None]

    def mark_residual(
        self, full: torch.Tensor, rows: torch.Tensor, selections: dict[int, ContourSelection]
    ) -> torch.Tensor:
        """(N, 2 L) e_J of parameter rows ``full`` (N, P) with the choice ``selections``."""
        parts = [full.new_zeros(full.shape[0], 0)]
        for j, marks in self.marks.items():
            target = self._marks_at(selections[j], full.shape[0], len(marks))
            parts.append(self._entries(self.joint_pixels(full, j, rows)[:, :, 1], target, rows))
        return torch.cat(parts, 1)

    def residual(self, full, selections=None, rows=None) -> torch.Tensor:
        """(N, M) residuals: :meth:`PriorFit.residual`, then e_J."""
        if rows is None:
            rows = torch.arange(full.shape[0], device=full.device)
        selections = selections or self.select(full, rows)
        base = super().residual(full, selections, rows)
        return torch.cat([base, self.mark_residual(full, rows, selections)], 1)

    def loss_units(self) -> torch.Tensor:
        """As :meth:`PriorFit.loss_units`; e_J is least squares."""
        inf = torch.full((self.batch, self.residual_layout.num_marks), torch.inf, **self.kw)
        return torch.cat([super().loss_units(), inf], 1)

    def residual_mask(self) -> torch.Tensor:
        """As :meth:`PriorFit.residual_mask`; e_J is always valid (zero where unmarked)."""
        base = super().residual_mask()
        return torch.cat([base, base.new_ones(self.batch, self.residual_layout.num_marks)], 1)

    def _mark_columns(self, free: torch.Tensor, j: int) -> torch.Tensor:
        """Positions in ``free`` of the columns posture j depends on (scales, its block)."""
        sl = self.layout.blocks[j].columns
        scale = free < self.layout.num_scale_params
        return (scale | ((free >= sl.start) & (free < sl.stop))).nonzero().flatten()

    def jacobian_blocks(self, free: torch.Tensor) -> list[tuple[slice, torch.Tensor]]:
        """As :meth:`PriorFit.jacobian_blocks`, with posture j's e_J on the scales and its own
        parameters."""
        out = super().jacobian_blocks(free)
        for j, rows in self._mark_rows().items():
            out.append((rows, self._mark_columns(free, j)))
        return out

    def _moving_columns(self, j: int) -> torch.Tensor:
        """(C,) the columns that can move posture j's marked joints standing on the floor: the
        scales of the segments above each joint and of the soles' segments and theirs (a
        joint centre moves with its ancestors' scales, a sole with its own too), the DOFs that
        move any of those segments, and the posture's root."""
        model, layout = self.model, self.layout
        parents = model.template.parents
        group = model.template.segment_group.tolist()
        soles = [int(model.template.vertex_segment[v]) for v in self.poser.soles]

        def above(s: int) -> list[int]:
            out, s = [], int(parents[s])
            while s >= 0:
                out.append(s)
                s = int(parents[s])
            return out

        joints = [int(s) for s in self._segments[j][:, 1].tolist()]
        segments = set(soles) | {a for s in joints + soles for a in above(s)}
        columns = {
            layout.scale_column(model.template.scale_groups[group[s]], axis)
            for s in segments
            for axis in "xyz"
        }
        block = layout.blocks[j]
        moves = model.chain.dof_moves[:, sorted(set(joints) | segments | set(soles))].any(1)
        for k, dof in enumerate(block.dofs):
            if bool(moves[dof]):
                columns.add(block.joints.start + k)
        columns.update(range(block.root.start, block.root.stop))
        return torch.tensor(sorted(c for c in columns if c is not None), device=model.device)

    def _mark_jacobian(
        self, full: torch.Tensor, free: torch.Tensor, j: int, rows: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """Posture j's marked joints' pixels (N, L, 2), their derivatives (N, L, 2, c) w.r.t.
        the free columns that can move them (``None`` where none does), and those columns'
        positions (c,) in ``free`` (forward-mode AD, the tangents folded into the batch)."""
        at = torch.isin(free, self._moving[j]).nonzero().flatten()
        n, c = full.shape[0], at.numel()
        if not c:  # nothing free moves the joints: their pixels alone
            return self.joint_pixels(full, j, rows)[:, :, 1], None, at
        seg = self._segments[j][:, 1]
        tangent = torch.zeros(n * c, full.shape[1], **self.kw)
        tangent[torch.arange(n * c), free[at].repeat(n)] = 1.0
        empty = torch.zeros(0, dtype=torch.long, device=full.device)
        with fwad.dual_level():
            dual = fwad.make_dual(full.repeat_interleave(c, dim=0), tangent)
            origins = self.pose_world(dual, j, rows.repeat_interleave(c), empty)[1]
            primal, tan = fwad.unpack_dual(origins)
        world = primal[::c, seg]
        d_world = tan[:, seg].reshape(n, c, -1, 3).permute(0, 2, 3, 1)  # (N, L, 3, c)
        pixels, d_pix = project_with_jacobian(world, d_world, self.camera[rows])
        return pixels, d_pix, at

    def jacobian_and_residual(self, full, free, selections, rows=None):
        """:meth:`PriorFit.jacobian_and_residual` with the e_J rows filled in."""
        if rows is None:
            rows = torch.arange(full.shape[0], device=full.device)
        jac, base = super().jacobian_and_residual(full, free, selections, rows)
        parts = [base]
        n = full.shape[0]
        for j, cols in self._mark_rows().items():
            target = self._marks_at(selections[j], n, len(self.marks[j]))
            pixels, d_pix, at = self._mark_jacobian(full, free, j, rows)
            parts.append(self._entries(pixels, target, rows))
            if at.numel():
                weight = self._mark_weights(target, rows)[..., None]
                jac[:, cols, at] = (weight * d_pix).reshape(n, -1, at.numel())
        return jac, torch.cat(parts, 1)

    @torch.no_grad()
    def mark_record(
        self, full: torch.Tensor, selections: dict[int, ContourSelection], i: int
    ) -> dict:
        """params.json's record of subject row ``i``'s marks at ``full`` (B, P) with the
        choice ``selections``: per posture and joint, the target pixel (``None`` where the
        limbs' crossing was not found or not trusted), the model joint's pixel and their
        distance."""
        rows = torch.arange(full.shape[0], device=full.device)[i : i + 1]
        out = {}
        for j, marks in self.marks.items():
            pixels = self.joint_pixels(full[i : i + 1], j, rows)[0, :, 1].tolist()
            target = self._marks_at(selections[j], full.shape[0], len(marks))[i].tolist()
            record = {}
            for m, bend in enumerate(marks):
                found = target[m][2] > 0
                record[bend.joint] = {
                    "target_px": [round(v, 2) for v in target[m][:2]] if found else None,
                    "model_px": [round(v, 2) for v in pixels[m]],
                    "offset_px": (round(math.dist(target[m][:2], pixels[m]), 2) if found else None),
                }
            out[f"pose{j}"] = record
        return out

    def shown(self, record: dict, i: int = 0) -> set[str]:
        """The measurements subject ``i``'s marks show (:data:`SHOWN_BY`), from its
        :meth:`mark_record`: those of every joint found and fitted within ``shown_px``
        (reference pixels, :attr:`image_scale`) of its mark."""
        limit = self.bend_options.shown_px / float(self.image_scale[i])
        out: set[str] = set()
        for joints in record.values():
            for joint, mark in joints.items():
                offset = mark["offset_px"]
                if offset is not None and offset <= limit:
                    out.update(SHOWN_BY.get(_kind(joint), ()))
        return out


def _kind(joint: str) -> str:
    """A joint's name without its side: ``"l_knee"`` -> ``"knee"``."""
    return joint.split("_", 1)[-1]
