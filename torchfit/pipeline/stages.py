"""Run the configured stage schedule on a batch, and the automatic start before it."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch

from torchfit.config.schema import Config
from torchfit.fit.problem import SilhouetteFit
from torchfit.fit.stages import solve_stage
from torchfit.solver import LMStatus

__all__ = ["StageRecord", "start_params", "run_stages", "FAILED_SOLVER_STATUS"]

log = logging.getLogger(__name__)

#: Solver statuses that mean the fit failed (no usable result).
FAILED_SOLVER_STATUS = frozenset({"NONFINITE", "LINALG"})


@dataclass
class StageRecord:
    """One subject's outcome of one stage (a row of ``params.json["stages"]``)."""

    stage: str
    status: str
    message: str
    cost: float
    iterations: int

    def to_dict(self) -> dict:
        """The params.json form."""
        return asdict(self)


def _status_name(code: int) -> str:
    try:
        return LMStatus(code).name
    except ValueError:
        return str(code)


def start_params(fit: SilhouetteFit, config: Config, masks: torch.Tensor, images: torch.Tensor):
    """The start of a batch: the template's, or the automatic guess (``fit.initial_guess``).

    Args:
        fit: the batch's problem.
        config: the run's config.
        masks: (B, J, H, W) silhouettes of the fitted postures.
        images: (B, J, 3, H, W) their images.

    Returns:
        (B, P) start parameters and, for the automatic guess, one
        :class:`torchfit.fit.initial_guess.StartInfo` per subject (else None).
    """
    if config.fit.initial_guess != "parts":
        return fit.initial_params(), None
    from torchfit.fit.initial_guess import parts_start

    return parts_start(fit, masks, images, config.parts)


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
    solver = config.solver
    records: list[list[StageRecord]] = [[] for _ in names]
    for si, stage in enumerate(config.fit.stages):
        options = solver.lm_options(stage.max_iter or solver.max_iter)
        tag = f"stage{si + 1}_{stage.name}"
        if config.fit.method == "minpack_rendered":
            from torchfit.fit.baseline import minpack_stage

            x, results = minpack_stage(fit, x, stage, options)
            per = [
                (int(r.status[0]), float(r.cost[0]), int(r.nfev[0]), r.message[0]) for r in results
            ]
        else:
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
                    solver.jacobian,
                    callback=_Callbacks(callbacks) if callbacks else None,
                )
            finally:
                if bar is not None:
                    bar.close()
            per = [
                (int(res.status[i]), float(res.cost[i]), int(res.n_iter[i]), res.message[i])
                for i in range(len(names))
            ]
        for i, (code, cost, iters, message) in enumerate(per):
            records[i].append(StageRecord(stage.name, _status_name(code), message, cost, iters))
        if any(_status_name(p[0]) in FAILED_SOLVER_STATUS for p in per):
            log.warning("%s: %s", tag, [p[3] for p in per])
    return x, records
