"""Run the configured stage schedule on a batch, and the automatic start before it.

After the last stage the postures of each subject are compared
(:func:`torchfit.fit.stages.pose_outliers` on their contour RMS): one that disagrees with the
others is down-weighted (``fit.pose_outlier_weight``) and the last stage runs once more
(``<name>_reweighted``) for the subjects with such a posture only. At the end, the down-weighted
postures, implausible body proportions (:mod:`torchfit.pipeline.checks`), scales on their
upper bound and the postures whose floor translation or yaw ended on its limit (when two or
more did) become the ``flags`` of the subject's last stage record, which the judge reads.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace

import torch

from torchfit.body.measure import measure_model
from torchfit.body.model import BodyModel
from torchfit.config.schema import Config
from torchfit.fit.bends import BendFit
from torchfit.fit.pose import template_layout
from torchfit.fit.prior import load_prior, posture_prior_dofs
from torchfit.fit.problem import SilhouetteFit
from torchfit.fit.stages import pose_contour_rms, pose_outliers, solve_stage
from torchfit.pipeline.checks import (
    SHOWN_BY_POSTURE,
    bound_flags,
    population_ranges,
    proportion_flags,
    proportion_outliers,
    root_bound_flags,
)
from torchfit.solver import LMStatus

__all__ = ["StageRecord", "start_params", "run_stages", "check_names", "FAILED_SOLVER_STATUS"]

log = logging.getLogger(__name__)

#: Solver statuses that mean the fit failed (no usable result).
FAILED_SOLVER_STATUS = frozenset({"NONFINITE", "LINALG"})


@dataclass
class StageRecord:
    """One subject's outcome of one stage (a row of ``params.json["stages"]``).

    ``flags`` (last stage only): what makes the fit doubtful though the solver converged
    (down-weighted postures, proportions, scales on bounds); written only when not empty.
    """

    stage: str
    status: str
    message: str
    cost: float
    iterations: int
    flags: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        """The params.json form."""
        out = asdict(self)
        if not self.flags:
            del out["flags"]
        return out


def _status_name(code: int) -> str:
    try:
        return LMStatus(code).name
    except ValueError:
        return str(code)


def start_params(
    fit: SilhouetteFit, config: Config, masks: torch.Tensor, images: list[torch.Tensor]
):
    """The start of a batch: the template's, or the automatic guess (``fit.initial_guess``).

    Args:
        fit: the batch's problem.
        config: the run's config.
        masks: (B, J, H, W) silhouettes of the fitted postures.
        images: B (J, 3, H, W) images of the fitted postures (stacked for the automatic guess
            only: a batch's images are 30 MB a subject in float32 at 720x576).

    Returns:
        (B, P) start parameters and, for the automatic guess, one
        :class:`torchfit.fit.initial_guess.StartInfo` per subject (else None).
    """
    if config.fit.initial_guess != "parts":
        return fit.initial_params(), None
    from torchfit.fit.initial_guess import parts_start

    return parts_start(fit, masks, torch.stack(images), config.parts)


class _Callbacks:
    """Several solver callbacks as one (stops when any asks to)."""

    def __init__(self, callbacks: list[Callable]) -> None:
        self.callbacks = callbacks

    def __call__(self, it) -> bool:
        stop = False
        for cb in self.callbacks:
            stop = bool(cb(it)) or stop
        return stop


class _IterationProgress:
    """Solver callback that advances a progress bar per iteration, with the cost."""

    def __init__(self, bar) -> None:
        self.bar = bar

    def __call__(self, it) -> bool:
        running = it.status == 0
        cost = it.cost[running] if bool(running.any()) else it.cost
        self.bar.update(1)
        self.bar.set_postfix(
            cost=f"{float(cost.median()):.4g}", running=f"{int(running.sum())}/{len(it.cost)}"
        )
        return False


def run_stages(
    fit: SilhouetteFit,
    x: torch.Tensor,
    config: Config,
    names: list[str],
    tb=None,
    progress: Callable[[str, int], object] | None = None,
) -> tuple[torch.Tensor, list[list[StageRecord]]]:
    """Run every stage of ``config.fit.stages`` from ``x`` (B, P).

    Args:
        fit: the batch's problem.
        x: (B, P) start parameters.
        config: the run's config (``fit.method``, ``fit.stages``, ``solver``).
        names: the subjects' names (TensorBoard tags).
        tb: optional :class:`torchfit.pipeline.tensorboard.TensorBoardCallback` of the run.
        progress: optional factory ``(description, total) -> bar`` (``update``,
            ``set_postfix``, ``close``, as tqdm's) for a bar per stage that advances with every
            solver iteration and shows the median cost of the subjects still running.

    Returns:
        (B, P) fitted parameters and, per subject, one :class:`StageRecord` per stage.
    """
    records: list[list[StageRecord]] = [[] for _ in names]
    fit.pose_weights.fill_(1.0)
    downweighted: list[dict[int, str]] = [{} for _ in names]
    stages = list(config.fit.stages)
    for si, stage in enumerate(stages):
        x = _stage_for(fit, x, config, stage, names, range(len(names)), si, records, tb, progress)
    if config.fit.method != "minpack_rendered":
        # postures are compared once the whole schedule has run (an earlier stage has not
        # fitted every segment yet); a subject with a new outlier, and only it, gets the last
        # stage once more, so that a subject's result does not depend on the others in its batch
        rerun = _reweight(fit, x, config, downweighted, names)
        if rerun:
            again = replace(stages[-1], name=f"{stages[-1].name}_reweighted")
            sub = fit.subset(rerun)
            x_sub = _stage_for(
                sub, x[rerun], config, again, names, rerun, len(stages), records, tb, progress
            )
            x = x.index_copy(0, torch.tensor(rerun, device=x.device), x_sub)
            _reweight(fit, x, config, downweighted, names)
    flags = _final_flags(fit, x, config, downweighted)
    for i, f in enumerate(flags):
        records[i][-1].flags = f
    fit.pose_weights.fill_(1.0)
    return x, records


def _stage_for(
    fit: SilhouetteFit,
    x: torch.Tensor,
    config: Config,
    stage,
    names: list[str],
    rows,
    si: int,
    records: list[list[StageRecord]],
    tb,
    progress,
) -> torch.Tensor:
    """Stage ``si`` for the subjects ``rows`` (the batch of ``fit`` and ``x``); appends their
    records and returns their (N, P) parameters."""
    solver = config.solver
    options = solver.lm_options(stage.max_iter or solver.max_iter)
    if stage.loss is not None:
        options = replace(options, loss=stage.loss)
    tag = f"stage{si + 1}_{stage.name}"
    own = [names[i] for i in rows]
    x, per = _run_stage(fit, x, config, stage, options, own, tag, tb, progress)
    for i, (code, cost, iters, message) in zip(rows, per, strict=True):
        records[i].append(StageRecord(stage.name, _status_name(code), message, cost, iters))
    if any(_status_name(p[0]) in FAILED_SOLVER_STATUS for p in per):
        log.warning("%s: %s", tag, [p[3] for p in per])
    return x


def _run_stage(fit, x, config, stage, options, names, tag, tb, progress):
    """One stage for the batch: (B, P) parameters and per subject (status, cost, iterations,
    message)."""
    if config.fit.method == "minpack_rendered":
        from torchfit.fit.baseline import minpack_stage

        x, results = minpack_stage(fit, x, stage, options)
        return x, [
            (int(r.status[0]), float(r.cost[0]), int(r.nfev[0]), r.message[0]) for r in results
        ]
    callbacks: list[Callable] = []
    if tb is not None:
        from torchfit.pipeline.tensorboard import TensorBoardCallback

        callbacks.append(TensorBoardCallback(tb.writer, tag, names, log_every=1))
    bar = None
    if progress is not None:
        bar = progress(f"{tag} ({len(names)} subjects)", options.max_iter)
        callbacks.append(_IterationProgress(bar))
    try:
        x, res = solve_stage(
            fit,
            x,
            stage,
            options,
            config.solver.jacobian,
            callback=_Callbacks(callbacks) if callbacks else None,
        )
    finally:
        if bar is not None:
            bar.close()
    return x, [
        (int(res.status[i]), float(res.cost[i]), int(res.n_iter[i]), res.message[i])
        for i in range(len(names))
    ]


def _reweight(
    fit: SilhouetteFit,
    x: torch.Tensor,
    config: Config,
    downweighted: list[dict[int, str]],
    names: list[str],
) -> list[int]:
    """Down-weight the postures that now disagree with the others; the subjects with a newly
    down-weighted posture."""
    opts = config.fit
    rms, _ = pose_contour_rms(fit, x)
    # pose_outlier_min_px is in reference pixels (fit.reference_px_per_m)
    reference = rms * fit.image_scale[:, None]
    outliers = pose_outliers(reference, opts.pose_outlier_k, opts.pose_outlier_min_px)
    med = rms.median(dim=1).values
    new: list[int] = []
    for i, k in outliers.nonzero().tolist():
        j = fit.poses[k]
        downweighted[i][j] = (
            f"pose{j} down-weighted: contour rms {float(rms[i, k]):.1f} px "
            f"vs median {float(med[i]):.1f}"
        )
        if float(fit.pose_weights[i, k]) == 1.0:
            fit.pose_weights[i, k] = opts.pose_outlier_weight
            new += [] if i in new else [i]
            log.info("%s: %s", names[i], downweighted[i][j])
    return new


def _final_flags(
    fit: SilhouetteFit, x: torch.Tensor, config: Config, downweighted: list[dict[int, str]]
) -> list[list[str]]:
    """Per subject, what makes its fit doubtful (see the module docstring)."""
    with torch.no_grad():
        scales = fit.model.expand_scales(fit.layout.group_scales(x))
        measures = measure_model(fit.model, scales)
    cols = range(fit.layout.num_scale_params)
    free = [c for c in cols if float(fit.lower[c]) < float(fit.upper[c])]
    names = [fit.layout.names[c].removeprefix("scale:") for c in free]
    ranges = population_ranges(_template_ratios(fit))
    out = []
    for i in range(x.shape[0]):
        values = {k: float(v[i]) for k, v in measures.items()}
        flags = [downweighted[i][j] for j in sorted(downweighted[i])]
        hard = proportion_flags(values)
        outliers = proportion_outliers(values, ranges)
        if isinstance(fit, BendFit) and any(o.key in fit.can_show for o in outliers):
            # a proportion the images show (a knee placed by its limbs) is not judged by the
            # population's percentiles, only by the hard limits
            shown = fit.shown(fit.mark_record(x, fit.select(x), i), i)
            outliers = [o for o in outliers if o.key not in shown]
        # lengths a posture shows end to end, where it was fitted with its full weight
        whole = {
            k for k, j in SHOWN_BY_POSTURE.items() if j in fit.poses and j not in downweighted[i]
        }
        outliers = [o for o in outliers if o.key not in whole]
        flags += hard or [o.describe() for o in outliers]
        flags += bound_flags([float(x[i, c]) for c in free], names, fit.scale_bounds)
        offsets = {j: fit.layout.root_offsets(x[i], j) for j in fit.poses}
        flags += root_bound_flags(offsets, fit.options.translation_max_m, fit.options.yaw_max_deg)
        out.append(flags)
    return out


def _template_ratios(fit: SilhouetteFit) -> dict[str, float]:
    """The template's own measurements over its height (the start's unit scales)."""
    start = fit.layout.initial(**fit.kw)[None]
    with torch.no_grad():
        m = measure_model(fit.model, fit.model.expand_scales(fit.layout.group_scales(start)))
    height = float(m["height_m"][0])
    return {k: float(v[0]) / height for k, v in m.items()}


def check_names(model: BodyModel, config: Config) -> None:
    """Stop the run, not each fit, at a name the template or the priors lack: the posture
    prior's joints, the population prior, each posture's free joints, the stages' scales.

    Raises:
        ConfigError: naming the key.
    """
    if config.fit.prior.pose_weight > 0:
        posture_prior_dofs(model, config.fit.prior)
    if config.fit.prior.weight > 0:
        load_prior(config.fit.prior.name)
    layout = template_layout(model, list(config.fit.poses), config.fit.free_joints)
    for stage in config.fit.stages:
        layout.scale_indices(stage.scales)
