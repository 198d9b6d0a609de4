"""TensorBoard logging of solver progress (the only module that imports TensorBoard).

:class:`TensorBoardCallback` is a :func:`torchfit.solver.levenberg_marquardt` callback that writes,
for every problem of the batch and every iteration, the cost, the damping and the step norm as
scalars ``{tag_prefix}/{name}/cost``, ``.../damping`` and ``.../step_norm`` (global step = the
solver iteration). Problems that have stopped are no longer logged.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from torch.utils.tensorboard import SummaryWriter

from torchfit.errors import TorchfitError
from torchfit.solver.result import LMIterate, LMStatus

__all__ = ["TensorBoardCallback"]


class TensorBoardCallback:
    """Log per-problem cost, damping and step norm of a batched solve to TensorBoard.

    Args:
        log_dir: a folder for a new ``SummaryWriter`` (created if missing), or a writer to use
            (then the caller closes it).
        tag_prefix: first part of every tag, e.g. ``"stage1"``.
        problem_names: one name per problem (length ``B``); default ``"0"``, ``"1"``, ….
        log_every: log every this many iterations (and always the last of each problem).

    Example:
        >>> with TensorBoardCallback("runs/demo/tb", "lm") as tb:
        ...     levenberg_marquardt(residual_fn, x0, callback=tb)
    """

    def __init__(
        self,
        log_dir: str | Path | SummaryWriter,
        tag_prefix: str = "solver",
        problem_names: Sequence[str] | None = None,
        log_every: int = 1,
    ) -> None:
        if isinstance(log_dir, SummaryWriter):
            self.writer = log_dir
            self._owns_writer = False
        elif isinstance(log_dir, (str, Path)):
            self.writer = SummaryWriter(log_dir=str(log_dir))
            self._owns_writer = True
        else:
            raise TorchfitError(
                f"log_dir: expected a path or a SummaryWriter, got {type(log_dir).__name__}"
            )
        if isinstance(log_every, bool) or not isinstance(log_every, int) or log_every < 1:
            raise TorchfitError(f"log_every: expected an int >= 1, got {log_every!r}")
        self.tag_prefix = tag_prefix.rstrip("/")
        self.problem_names = list(problem_names) if problem_names is not None else None
        self.log_every = log_every
        self._done: set[int] = set()  # problems whose final iteration is written

    def _names(self, batch: int) -> list[str]:
        if self.problem_names is None:
            return [str(b) for b in range(batch)]
        if len(self.problem_names) != batch:
            raise TorchfitError(
                f"problem_names: expected {batch} names (one per problem), "
                f"got {len(self.problem_names)}"
            )
        return self.problem_names

    def __call__(self, it: LMIterate) -> bool:
        """Write this iteration's scalars; never asks the solver to stop."""
        names = self._names(it.cost.shape[0])
        if it.iteration == 1:
            self._done = set()  # a new solve
        cost = it.cost.tolist()
        damping = it.damping.tolist()
        step = it.step_norm.tolist()
        status = it.status.tolist()
        for b, name in enumerate(names):
            just_done = status[b] != LMStatus.RUNNING
            if it.iteration % self.log_every and not just_done:
                continue
            if b in self._done:
                continue
            tag = f"{self.tag_prefix}/{name}"
            self.writer.add_scalar(f"{tag}/cost", cost[b], it.iteration)
            self.writer.add_scalar(f"{tag}/damping", damping[b], it.iteration)
            self.writer.add_scalar(f"{tag}/step_norm", step[b], it.iteration)
            if just_done:
                self._done.add(b)
        return False

    def add_image(self, tag: str, image, step: int = 0) -> None:
        """Log an (H, W, 3) uint8 RGB image (e.g. a fit overlay)."""
        self.writer.add_image(tag, image, step, dataformats="HWC")

    def add_scalar(self, tag: str, value: float, step: int = 0) -> None:
        """Log one scalar (e.g. a final per-pose residual)."""
        self.writer.add_scalar(tag, value, step)

    def flush(self) -> None:
        """Write pending events to disk."""
        self.writer.flush()

    def close(self) -> None:
        """Flush, and close the writer if this object created it."""
        self.writer.flush()
        if self._owns_writer:
            self.writer.close()

    def __enter__(self) -> TensorBoardCallback:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
