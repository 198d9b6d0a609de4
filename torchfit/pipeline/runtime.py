"""Process-wide runtime settings of a run: torch threads, the allocator, dtype and device."""

from __future__ import annotations

import logging
import os

import torch

from torchfit.config.schema import RunConfig
from torchfit.errors import ConfigError
from torchfit.fit.contour_pool import set_contour_workers, start_contour_workers
from torchfit.solver import keep_heap

__all__ = ["apply_runtime", "torch_dtype", "cpu_count", "local_threads", "contour_workers_for"]

log = logging.getLogger(__name__)


def torch_dtype(name: str) -> torch.dtype:
    """``"float32"`` / ``"float64"`` as a torch dtype."""
    return torch.float64 if name == "float64" else torch.float32


def cpu_count() -> int:
    """The CPUs this process may run on (its affinity mask, else the machine's)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def local_threads(run: RunConfig, cores: int | None = None) -> int:
    """Torch threads of a local run: ``run.num_threads``; else the CPUs shared by
    ``run.workers`` processes (default 1), so that threads x workers <= CPUs, and no more than
    ``OMP_NUM_THREADS`` where the environment sets it."""
    if run.num_threads:
        return run.num_threads
    cores = cpu_count() if cores is None else cores
    threads = max(1, cores // (run.workers or 1))
    omp = os.environ.get("OMP_NUM_THREADS", "")
    return min(threads, int(omp)) if omp.isdigit() and int(omp) > 0 else threads


def contour_workers_for(run: RunConfig, cores: int | None = None) -> int:
    """The contour choice's worker processes: ``run.contour_workers``; else none on the CPU
    and, on a GPU, the CPUs beside the fit's own (``cores - 1``)."""
    if run.contour_workers is not None:
        return run.contour_workers
    if torch.device(run.device).type == "cpu":
        return 0
    return max(0, (cpu_count() if cores is None else cores) - 1)


def apply_runtime(run: RunConfig) -> None:
    """Set the torch thread count (:func:`local_threads`) and start the contour choice's
    worker processes (:func:`contour_workers_for`; a local run's), check the device and set
    glibc's heap policy as ``run`` asks.

    Raises:
        ConfigError: ``run.device`` names a device torch cannot use here.
    """
    torch.set_num_threads(local_threads(run))
    try:
        device = torch.device(run.device)
    except RuntimeError as exc:
        raise ConfigError(f"run.device: {exc}") from None
    if device.type == "cuda" and run.executor == "local" and not torch.cuda.is_available():
        raise ConfigError(f"run.device: {run.device!r} but torch sees no CUDA device here")
    # with Ray the fits run in the tasks, which set their own
    set_contour_workers(contour_workers_for(run) if run.executor == "local" else 0)
    start_contour_workers()  # they start while the subjects are read and segmented
    if run.keep_heap and not keep_heap():
        log.warning("run.keep_heap: the C library is not glibc; the setting has no effect")
