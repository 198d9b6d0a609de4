"""TensorBoard logging of solver progress (the only module that imports TensorBoard).

:class:`TensorBoardCallback` is a :func:`torchfit.solver.levenberg_marquardt` callback that writes,
for every problem of the batch and every iteration, the cost, the damping and the step norm as
scalars ``{tag_prefix}/{name}/cost``, ``.../damping`` and ``.../step_norm`` (global step = the
solver iteration). Problems that have stopped are no longer logged.

TensorBoard is a side channel of a run: when its event file cannot be written (a full or
read-only disk), logging stops with one warning naming the folder and the run goes on. The
event file is written by a background thread of TensorBoard's ``EventFileWriter``; its
failure is reported by the next call from the run (the thread's own traceback is not
printed).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

from torch.utils.tensorboard import SummaryWriter

from torchfit.errors import OutputError, TorchfitError
from torchfit.solver.result import LMIterate, LMStatus

__all__ = ["TensorBoardCallback"]

log = logging.getLogger(__name__)

_previous_hook = threading.excepthook


def _quiet_writer_thread(args: threading.ExceptHookArgs) -> None:
    """``threading.excepthook`` that leaves TensorBoard's event writer thread's failure to the
    main thread (which reports it in one line) and hands every other thread to the previous
    hook."""
    thread = type(args.thread).__name__ if args.thread is not None else ""
    if thread == "_AsyncWriterThread" and isinstance(args.exc_value, Exception):
        log.debug("TensorBoard writer thread: %s", args.exc_value)
        return
    _previous_hook(args)


def _guarded(writer: SummaryWriter, action: Callable[[], object], always: bool = False) -> None:
    """Run ``action`` (a call on ``writer``) unless the writer has failed (or ``always``); on
    the first failure, warn once and stop using the writer."""
    failed = getattr(writer, "_torchfit_failed", False)
    if failed and not always:
        return
    try:
        action()
    except Exception as exc:  # OSError from the disk, or what the writer thread stored
        writer._torchfit_failed = True
        if not failed:
            log.warning("TensorBoard logging stopped: cannot write to %s: %s", writer.log_dir, exc)


class TensorBoardCallback:
    """Log per-problem cost, damping and step norm of a batched solve to TensorBoard.

    Args:
        log_dir: a folder for a new ``SummaryWriter`` (created if missing; OutputError when it
            cannot be), or a writer to use (then the caller closes it).
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
            if threading.excepthook is not _quiet_writer_thread:
                threading.excepthook = _quiet_writer_thread
            try:
                self.writer = SummaryWriter(log_dir=str(log_dir))
            except OSError as exc:
                raise OutputError(f"cannot create {log_dir}: {exc.strerror or exc}") from None
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
            for key, values in (("cost", cost), ("damping", damping), ("step_norm", step)):
                self.add_scalar(f"{tag}/{key}", values[b], it.iteration)
            if just_done:
                self._done.add(b)
        return False

    def add_image(self, tag: str, image, step: int = 0) -> None:
        """Log an (H, W, 3) uint8 RGB image (e.g. a fit overlay)."""
        _guarded(self.writer, lambda: self.writer.add_image(tag, image, step, dataformats="HWC"))

    def add_scalar(self, tag: str, value: float, step: int = 0) -> None:
        """Log one scalar (e.g. a final per-pose residual)."""
        _guarded(self.writer, lambda: self.writer.add_scalar(tag, value, step))

    def flush(self) -> None:
        """Write pending events to disk."""
        _guarded(self.writer, self.writer.flush)

    def close(self) -> None:
        """Flush, and close the writer if this object created it."""
        self.flush()
        if self._owns_writer:
            _guarded(self.writer, self.writer.close, always=True)

    def __enter__(self) -> TensorBoardCallback:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
