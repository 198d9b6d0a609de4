"""Worker processes for the contour choice.

The contour choice (:func:`torchfit.fit.model_contour.select_contours`) draws every image's
projected silhouette edges, traces their outline and queries a k-d tree: CPU work, one image
at a time, and on a GPU fit the larger part of the time. Its images are independent, so it can
spread them over processes. Each image is chosen by the same function in a worker as in this
process, so the choice, and the fit, are the same bit for bit.

The pool is process-wide and made at first use: :func:`set_contour_workers` sets its size
(0, the default: no pool, every image chosen here). Workers are spawned, not forked (a forked
copy of a process that runs torch's thread pools or CUDA can hang), each with one torch
thread; the pool ends with the process or at the next :func:`set_contour_workers`. Spawned
workers import the main module, so a script that uses them keeps its code under
``if __name__ == "__main__":``. A call whose pool breaks (a worker killed, or a script without
that guard) does its work in this process; after :data:`MAX_BROKEN` broken pools the process
stops using workers, with a warning.
"""

from __future__ import annotations

import atexit
import logging
import multiprocessing
from collections.abc import Callable, Sequence
from concurrent.futures import BrokenExecutor, ProcessPoolExecutor

__all__ = ["set_contour_workers", "contour_workers", "start_contour_workers", "map_chunks"]

log = logging.getLogger(__name__)

_size = 0
_pool: ProcessPoolExecutor | None = None
_broken = 0

#: Broken pools after which a process stops using workers.
MAX_BROKEN = 2


def set_contour_workers(n: int) -> None:
    """Choose the contour choice's worker processes (0: none, every image in this process).

    Raises:
        ValueError: ``n`` is negative.
    """
    global _size, _broken
    if n < 0:
        raise ValueError(f"contour workers: expected an integer >= 0, got {n!r}")
    if n != _size:
        _shutdown()
        _size = n
        _broken = 0


def contour_workers() -> int:
    """The number of contour worker processes (0: none)."""
    return _size


def start_contour_workers() -> list:
    """Start the workers now, without waiting for them (each imports torch: seconds), so that
    they start while the caller reads and segments; returns one future per worker, done when
    it is up."""
    if _size == 0:
        return []
    return [_executor().submit(_ready) for _ in range(_size)]


def _executor() -> ProcessPoolExecutor:
    global _pool
    if _pool is None:
        _pool = ProcessPoolExecutor(
            _size, mp_context=multiprocessing.get_context("spawn"), initializer=_init_worker
        )
    return _pool


def _ready() -> bool:
    return True


def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)


def _shutdown() -> None:
    global _pool
    if _pool is not None:
        _pool.shutdown(wait=True, cancel_futures=True)
        _pool = None


atexit.register(_shutdown)


def map_chunks(fn: Callable, items: Sequence, shared: tuple) -> list:
    """``[fn(item, *shared) for item in items]``, over the worker processes where there are
    some and more than one item; else in this process.

    ``fn`` must be a module-level function; ``items`` are sent in one chunk per worker,
    ``shared`` once with each chunk. Where a worker dies, this call does the work itself and
    the next one starts a new pool; an error that ``fn`` raises reaches the caller.
    """
    global _pool, _size, _broken
    if _size == 0 or len(items) < 2:
        return [fn(item, *shared) for item in items]
    n = -(-len(items) // _size)
    chunks = [items[i : i + n] for i in range(0, len(items), n)]
    try:
        parts = _executor().map(_run_chunk, [(fn, c, shared) for c in chunks])
        return [out for part in parts for out in part]
    except BrokenExecutor as exc:
        # a worker died (killed, out of memory): the same work here, and a new pool next time;
        # a second broken pool ends the workers for this process (a script that starts them at
        # import, without `if __name__ == "__main__":`, breaks every pool it makes)
        _pool.shutdown(wait=False, cancel_futures=True)
        _pool = None
        _broken += 1
        if _broken >= MAX_BROKEN:
            log.warning(
                "contour worker processes died twice (%s); the contour choice stays in this "
                "process from now on. A script that runs the fit with workers needs its code "
                'under `if __name__ == "__main__":` (they import the main module)',
                exc,
            )
            _size = 0
        else:
            log.warning("a contour worker process died (%s); choosing in this process", exc)
        return [fn(item, *shared) for item in items]


def _run_chunk(task: tuple) -> list:
    fn, chunk, shared = task
    return [fn(item, *shared) for item in chunk]
