"""The population prior over the body's log scales, and the known facts of a subject.

The prior (a file made by ``tools/make_prior.py`` from ANSUR II, shipped in
``torchfit/body/priors/``) is a Gaussian over ``log s`` for some of the template's scale
entries (``group:axis``), one component per sex and one for a person of unknown sex. The fit
adds its residuals ``e_S = weight * L^-1 (log s - mu)`` (``L`` the lower Cholesky factor of the
component's covariance), so that least squares is a MAP estimate. A known height adds
``e_H = (height(s) - height_m) / tolerance``: one tolerance of height error costs as much as a
posture whose contour is one pixel off on average.

:class:`PriorFit` is :class:`~torchfit.fit.problem.SilhouetteFit` with both appended after e_B
(:class:`~torchfit.fit.layout.ResidualLayout` owns where they live).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.autograd.forward_ad as fwad

from torchfit.body.model import BodyModel
from torchfit.body.template import TEMPLATE_DIR
from torchfit.errors import ConfigError, DataError
from torchfit.fit.layout import ParamLayout
from torchfit.fit.person import PersonData
from torchfit.fit.problem import FitOptions, SilhouetteFit

__all__ = [
    "PRIOR_DIR",
    "SEXES",
    "PriorOptions",
    "KnownFacts",
    "ScalePrior",
    "load_prior",
    "neutral_height",
    "posture_prior_dofs",
    "PriorFit",
]

#: Where the shipped priors live (``<name>.json``).
PRIOR_DIR = TEMPLATE_DIR.parent / "priors"
#: The sexes a prior has a component for (``any`` is used when the sex is not known).
SEXES: tuple[str, ...] = ("female", "male")


@dataclass(frozen=True)
class PriorOptions:
    """The population prior and the known facts in the fit.

    Attributes:
        name: a shipped prior (``ansur2``) or a path to a prior JSON file.
        weight: the prior's weight (0: no prior). Its residuals count one standard deviation
            of the population as ``weight`` pixels of contour RMS in one posture.
        height_tolerance_m: the height error (metres) that costs as much as one pixel of
            contour RMS in one posture, when ``subject.yaml`` gives the height.
        entries: the prior's scale entries (``group:axis``) the fit uses (their marginal);
            None: all of the file's.
        pose_weight: the posture prior's weight (0: none). It adds, for every free angle of
            the joints ``pose_joints`` in every posture, ``pose_weight * (angle - nominal) /
            pose_sigma_deg``: a joint ``pose_sigma_deg`` off its posture's nominal angle
            costs as much as ``pose_weight`` pixels of contour RMS in one posture.
        pose_sigma_deg: the posture prior's spread, degrees.
        pose_joints: the DOFs it holds: a limb's by name without the side
            (``shoulder_flexion`` holds ``l_shoulder_flexion`` and ``r_shoulder_flexion``),
            others by their own name (``vc4_tilt``).
    """

    name: str = "ansur2"
    weight: float = 0.0
    height_tolerance_m: float = 0.005
    entries: tuple[str, ...] | None = None
    pose_weight: float = 0.0
    pose_sigma_deg: float = 15.0
    pose_joints: tuple[str, ...] = (
        "shoulder_flexion",
        "shoulder_abduct",
        "shoulder_twisting",
        "elbow_flexion",
        "hip_flexion",
        "knee_flexion",
        "ankle_flexion",
    )

    def __post_init__(self) -> None:
        if not (math.isfinite(self.weight) and self.weight >= 0):
            raise ConfigError(f"fit.prior.weight: expected a number >= 0, got {self.weight!r}")
        if not (math.isfinite(self.height_tolerance_m) and self.height_tolerance_m > 0):
            raise ConfigError(
                f"fit.prior.height_tolerance_m: expected a number > 0, got "
                f"{self.height_tolerance_m!r}"
            )
        if not (math.isfinite(self.pose_weight) and self.pose_weight >= 0):
            raise ConfigError(
                f"fit.prior.pose_weight: expected a number >= 0, got {self.pose_weight!r}"
            )
        if not (math.isfinite(self.pose_sigma_deg) and self.pose_sigma_deg > 0):
            raise ConfigError(
                f"fit.prior.pose_sigma_deg: expected a number > 0, got {self.pose_sigma_deg!r}"
            )


@dataclass(frozen=True)
class KnownFacts:
    """What ``subject.yaml`` says about a subject (None: not given)."""

    height_m: float | None = None
    weight_kg: float | None = None
    sex: str | None = None

    @property
    def empty(self) -> bool:
        """True when nothing is known."""
        return self.height_m is None and self.weight_kg is None and self.sex is None

    def to_dict(self) -> dict:
        """The given facts only."""
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass(frozen=True)
class ScalePrior:
    """A loaded prior restricted to a template's scale entries.

    Attributes:
        name: the prior's name.
        entries: K scale entries ``group:axis``.
        mean: component -> (K,) mean of ``log s`` times the template height (log metres).
        covariance: component -> (K, K) covariance of ``log s``.
    """

    name: str
    entries: tuple[str, ...]
    mean: dict[str, torch.Tensor]
    covariance: dict[str, torch.Tensor]

    def restrict(self, entries: Sequence[str]) -> ScalePrior:
        """The marginal prior of some of the entries (in the given order)."""
        idx = torch.tensor([self.entries.index(e) for e in entries], dtype=torch.long)
        return ScalePrior(
            self.name,
            tuple(entries),
            {c: m[idx] for c, m in self.mean.items()},
            {c: v[idx][:, idx] for c, v in self.covariance.items()},
        )

    @staticmethod
    def component(sex: str | None) -> str:
        """The component of a sex (``any`` when unknown)."""
        return sex if sex in SEXES else "any"


def load_prior(name_or_path: str | Path) -> ScalePrior:
    """Load a shipped prior by name (``"ansur2"``) or a prior JSON file.

    Raises:
        ConfigError: unknown name, unreadable or malformed file.
    """
    path = Path(name_or_path)
    if path.suffix.lower() != ".json":
        path = PRIOR_DIR / f"{name_or_path}.json"
        if not path.is_file():
            shipped = sorted(p.stem for p in PRIOR_DIR.glob("*.json"))
            raise ConfigError(
                f"fit.prior.name: unknown prior {str(name_or_path)!r}: expected one of "
                f"{shipped} or a path to a .json file"
            )
    try:
        doc = json.loads(path.read_text())
        entries = tuple(doc["entries"])
        mean, cov = {}, {}
        for comp in (*SEXES, "any"):
            c = doc["components"][comp]
            chol = torch.tensor(c["cholesky"], dtype=torch.float64)
            mean[comp] = torch.tensor(c["mean"], dtype=torch.float64)
            cov[comp] = chol @ chol.T
            if mean[comp].shape != (len(entries),) or chol.shape != (len(entries),) * 2:
                raise ValueError(f"component {comp!r} does not match the {len(entries)} entries")
        offsets = (doc.get("calibration") or {}).get("offsets", {})
        shift = torch.tensor([float(offsets.get(e, 0.0)) for e in entries], dtype=torch.float64)
        mean = {c: m + shift for c, m in mean.items()}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{path}: not a valid prior file: {exc}") from exc
    return ScalePrior(doc.get("name", path.stem), entries, mean, cov)


def neutral_height(model: BodyModel, layout: ParamLayout, full: torch.Tensor) -> torch.Tensor:
    """(N,) floor to head top of the neutral body of parameter rows ``full`` (N, P), as
    :func:`torchfit.body.measure.measure_model` measures it (differentiable, forward mode
    included)."""
    scales = model.expand_scales(layout.group_scales(full))
    p = model.zeros(full.shape[0])
    joints = model.joint_positions(
        model(scales, p["joint_angles"], p["root_translation"], p["root_rotation"])
    )
    floor = torch.minimum(joints["l_sole"][:, 2], joints["r_sole"][:, 2])
    return joints["head_top"][:, 2] - floor


def posture_prior_dofs(model: BodyModel, options: PriorOptions) -> set[str]:
    """The template DOF names the posture prior holds (``options.pose_joints``).

    Raises:
        ConfigError: a name that is no joint of the template.
    """
    names = set(model.dof_names)
    unknown = [d for d in options.pose_joints if not {d, f"l_{d}", f"r_{d}"} & names]
    if unknown:
        raise ConfigError(
            f"fit.prior.pose_joints: {unknown} name no joint of template "
            f"{model.template.name!r} (a limb's joints without the side, e.g. "
            f"'elbow_flexion', or a joint's own name, e.g. 'vc4_tilt')"
        )
    return {n for d in options.pose_joints for n in (d, f"l_{d}", f"r_{d}")} & names


def _free_positions(columns: torch.Tensor, free: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The entries of ``columns`` (parameter columns) that are free, and their positions in
    ``free`` (the stage's free columns, each listed once)."""
    entries, at = (columns[:, None] == free[None, :].to(columns.device)).nonzero(as_tuple=True)
    return entries, at


class PriorFit(SilhouetteFit):
    """:class:`SilhouetteFit` plus the prior's residuals e_S and the known height's e_H.

    Args:
        model, person, options, scale_bounds: as :class:`SilhouetteFit`.
        prior: the population prior (None: no e_S).
        prior_options: the prior's weight and the height tolerance.
        facts: one :class:`KnownFacts` per subject (default: nothing known).
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
    ) -> None:
        super().__init__(model, person, options, scale_bounds)
        self.prior_options = prior_options = prior_options or PriorOptions()
        self.facts = list(facts) if facts is not None else [KnownFacts()] * self.batch
        if len(self.facts) != self.batch:
            raise DataError(f"facts: expected {self.batch} entries, got {len(self.facts)}")
        kw = self.kw
        wanted = prior_options.entries
        if prior is not None and wanted is not None:
            unknown = sorted(set(wanted) - set(prior.entries))
            if unknown:
                raise ConfigError(
                    f"fit.prior.entries: {unknown} not in prior {prior.name!r} "
                    f"(entries: {list(prior.entries)})"
                )
        chosen = [e for e in (prior.entries if prior else ()) if wanted is None or e in wanted]
        present = [e for e in chosen if self._column(e) is not None]
        self.prior = prior.restrict(present) if prior is not None and present else None
        self.prior_columns = torch.tensor(
            [self._column(e) for e in present], dtype=torch.long, device=model.device
        )
        if self.prior is not None:
            template_height = float(
                neutral_height(model, self.layout, self.layout.initial(**kw)[None])[0]
            )
            comps = [ScalePrior.component(f.sex) for f in self.facts]
            chol = {c: torch.linalg.cholesky(v) for c, v in self.prior.covariance.items()}
            eye = torch.eye(len(present), dtype=torch.float64)
            inv = {c: torch.linalg.solve_triangular(v, eye, upper=False) for c, v in chol.items()}
            self.prior_mu = torch.stack(
                [self.prior.mean[c] - math.log(template_height) for c in comps]
            ).to(**kw)
            self.prior_inv = torch.stack([inv[c] for c in comps]).to(**kw)
            self.prior_components = comps
        heights = [f.height_m if f.height_m is not None else math.nan for f in self.facts]
        self.known_height = torch.tensor(heights, **kw)
        self._init_pose_prior()
        self.residual_layout = self.layout.residual_layout(
            person.contour_lengths,
            len(present) if self.prior is not None else 0,
            1,
            int(self.pose_prior_columns.numel()),
        )

    def _init_pose_prior(self) -> None:
        """The parameter columns the posture prior holds and their nominal angles."""
        opts = self.prior_options
        columns, nominal = [], []
        if opts.pose_weight > 0:
            wanted = posture_prior_dofs(self.model, opts)
            for j in self.poses:
                block = self.layout.blocks[j]
                for k, dof in enumerate(block.dofs):
                    if self.model.dof_names[dof] in wanted:
                        columns.append(block.joints.start + k)
                        nominal.append(float(self.poser.nominal[j][dof]))
        self.pose_prior_columns = torch.tensor(columns, dtype=torch.long, device=self.model.device)
        self.pose_prior_nominal = torch.tensor(nominal, **self.kw)
        self.pose_prior_scale = opts.pose_weight / math.radians(opts.pose_sigma_deg)

    def _column(self, entry: str) -> int | None:
        group, _, axis = entry.partition(":")
        return self.layout.scale_column(group, axis)

    def _arguments(self, index: list[int]) -> dict:
        return {
            **super()._arguments(index),
            "prior": self.prior,
            "prior_options": self.prior_options,
            "facts": [self.facts[i] for i in index],
        }

    # ------------------------------------------------------------------------------------
    def prior_residual(self, full: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """(N, K) e_S of parameter rows ``full`` (N, P) of the subjects ``rows``."""
        if self.prior is None:
            return full.new_zeros(full.shape[0], 0)
        logs = full[:, self.prior_columns].clamp_min(1e-3).log() - self.prior_mu[rows]
        # products and a row sum, not a batched matrix product (which rounds a subject's row
        # differently alone than beside others)
        return self.prior_options.weight * (self.prior_inv[rows] * logs[:, None, :]).sum(-1)

    def height_residual(self, full: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """(N, 1) e_H (zero where the height is not known)."""
        target = self.known_height[rows]
        known = ~torch.isnan(target)
        if not bool(known.any()):
            return full.new_zeros(full.shape[0], 1)
        h = neutral_height(self.model, self.layout, full)
        r = (h - torch.where(known, target, h)) / self.prior_options.height_tolerance_m
        return torch.where(known, r, torch.zeros_like(r))[:, None]

    def pose_prior_residual(self, full: torch.Tensor) -> torch.Tensor:
        """(N, A) e_A of parameter rows ``full`` (N, P)."""
        angles = full[:, self.pose_prior_columns]
        return (angles - self.pose_prior_nominal) * self.pose_prior_scale

    def _extra_residuals(self, full: torch.Tensor, rows: torch.Tensor) -> list[torch.Tensor]:
        return [
            self.prior_residual(full, rows),
            self.height_residual(full, rows),
            self.pose_prior_residual(full),
        ]

    def residual(self, full, selections=None, rows=None) -> torch.Tensor:
        """(N, M) residuals: :meth:`SilhouetteFit.residual`, then e_S, e_H and e_A."""
        if rows is None:
            rows = torch.arange(full.shape[0], device=full.device)
        base = super().residual(full, selections, rows)
        return torch.cat([base, *self._extra_residuals(full, rows)], 1)

    def _num_extra(self) -> int:
        rl = self.residual_layout
        return rl.num_prior + rl.num_facts + rl.num_pose_prior

    def loss_units(self) -> torch.Tensor:
        """As :meth:`SilhouetteFit.loss_units`; e_S, e_H and e_A are least squares."""
        inf = torch.full((self.batch, self._num_extra()), torch.inf, **self.kw)
        return torch.cat([super().loss_units(), inf], 1)

    def residual_mask(self) -> torch.Tensor:
        """As :meth:`SilhouetteFit.residual_mask`; e_S, e_H and e_A are always valid."""
        base = super().residual_mask()
        return torch.cat([base, base.new_ones(self.batch, self._num_extra())], 1)

    def jacobian_blocks(self, free: torch.Tensor) -> list[tuple[slice, torch.Tensor]]:
        """As :meth:`SilhouetteFit.jacobian_blocks`, with e_S and e_H on the scales and e_A
        on the angles it holds."""
        rl = self.residual_layout
        out = super().jacobian_blocks(free)
        scale = (free < self.layout.num_scale_params).nonzero().flatten()
        for rows in (rl.prior, rl.facts):
            if rows.stop > rows.start:
                out.append((rows, scale))
        if rl.num_pose_prior:
            held = torch.isin(free, self.pose_prior_columns).nonzero().flatten()
            if held.numel():
                out.append((rl.pose_prior, held))
        return out

    def jacobian_and_residual(self, full, free, selections, rows=None):
        """:meth:`SilhouetteFit.jacobian_and_residual` with the e_S and e_H rows filled in."""
        if rows is None:
            rows = torch.arange(full.shape[0], device=full.device)
        jac, base = super().jacobian_and_residual(full, free, selections, rows)
        r = torch.cat([base, *self._extra_residuals(full, rows)], 1)
        rl = self.residual_layout
        held, at = _free_positions(self.pose_prior_columns, free)
        jac[:, rl.pose_prior.start + held, at] = self.pose_prior_scale
        if self.prior is not None and self.prior_options.weight > 0:
            s = full[:, self.prior_columns].clamp_min(1e-3)
            d = self.prior_options.weight * self.prior_inv[rows] / s[:, None, :]  # (N, K, K)
            entries, at = _free_positions(self.prior_columns, free)
            jac[:, rl.prior, at] = d[:, :, entries]
        known = ~torch.isnan(self.known_height[rows])
        scale_pos = (free < self.layout.num_scale_params).nonzero().flatten()
        if bool(known.any()) and scale_pos.numel():
            n, c = full.shape[0], scale_pos.numel()
            tangent = torch.zeros(n * c, full.shape[1], **self.kw)
            tangent[torch.arange(n * c), free[scale_pos].repeat(n)] = 1.0
            with fwad.dual_level():
                dual = fwad.make_dual(full.repeat_interleave(c, dim=0), tangent)
                tan = fwad.unpack_dual(neutral_height(self.model, self.layout, dual)).tangent
            dh = tan.reshape(n, c) / self.prior_options.height_tolerance_m
            jac[:, rl.facts.start, scale_pos] = dh * known[:, None].to(dh)
        return jac, r
