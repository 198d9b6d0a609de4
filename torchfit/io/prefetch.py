"""Compute an iterator's next items ahead of the consumer: in a background thread
(:func:`prefetch`) or in a second process (:func:`prefetch_process`).

The tracker reads and segments frame ``t + 1`` while it fits frame ``t``. The image decoding
and the tensor kernels release the interpreter lock, but both sides are made of many small
operations whose Python part holds it: in a thread, the tracker's frames took about 17 % longer
than without the other work beside them. A process overlaps fully, at the cost of its start
(immediate where it forks) and of pickling each item across.
"""

from __future__ import annotations

import os
import pickle
import queue
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

__all__ = ["prefetch", "prefetch_process"]

T = TypeVar("T")
_END = object()
_POLL_S = 0.1


class _Raised:
    """An exception of the source, carried to the consumer in its place."""

    def __init__(self, error: BaseException) -> None:
        self.error = error


def _put(ready, item, stopped: Callable[[], bool]) -> bool:
    """Put ``item`` on the bounded queue ``ready``, waiting while it is full, unless
    ``stopped()`` says the consumer no longer wants it (then False)."""
    while not stopped():
        try:
            ready.put(item, timeout=_POLL_S)
            return True
        except queue.Full:
            continue
    return False


def prefetch(items: Iterable[T], depth: int = 2) -> Iterator[T]:
    """Yield ``items`` in order, each computed up to ``depth`` items ahead of the consumer.

    Args:
        items: any iterable; it is iterated in one background thread.
        depth: how many finished items may wait (0: no thread, ``items`` as they are).

    An exception raised by ``items`` is raised here in place of the item it stopped, after the
    items before it. Closing the returned generator (or leaving a loop over it) stops the
    thread once its current item is done.
    """
    if depth < 0:
        raise ValueError(f"prefetch: depth must be >= 0, got {depth}")
    if depth == 0:
        yield from items
        return
    ready: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(item) -> bool:
        return _put(ready, item, stop.is_set)

    def work() -> None:
        try:
            for item in items:
                if not put(item):
                    return
        except BaseException as error:  # handed to the consumer, raised there
            put(_Raised(error))
            return
        put(_END)

    thread = threading.Thread(target=work, name="torchfit-prefetch", daemon=True)
    thread.start()
    try:
        while True:
            item = ready.get()
            if item is _END:
                return
            if isinstance(item, _Raised):
                raise item.error
            yield item
    finally:
        stop.set()
        thread.join()


def _serve(source, args, ready, threads: int, parent: int) -> None:
    """The process side of :func:`prefetch_process`."""
    import torch

    torch.set_num_threads(threads)

    def gone() -> bool:
        if os.getppid() == parent:
            return False
        ready.cancel_join_thread()  # the consumer was killed: exit without flushing what
        return True  # nobody will read

    def put(message) -> bool:
        return _put(ready, message, gone)

    try:
        for item in source(*args):
            # as bytes: the queue's own pickler would share tensors through file descriptors,
            # which must outlive this process
            if not put(("item", pickle.dumps(item, pickle.HIGHEST_PROTOCOL))):
                return
    except BaseException as error:  # handed to the consumer, raised there
        try:
            message = pickle.dumps(error, pickle.HIGHEST_PROTOCOL)
        except Exception:  # an error that does not pickle: its type and message
            message = pickle.dumps(RuntimeError(f"{type(error).__name__}: {error}"))
        put(("error", message))
        return
    put(("end", None))


def prefetch_process(
    source: Callable[..., Iterable[T]],
    *args,
    depth: int = 2,
    threads: int = 1,
    daemon: bool = True,
) -> Iterator[T]:
    """Yield the items of ``source(*args)``, computed in a separate process up to ``depth``
    items ahead of the consumer. The process starts when this is called (several of them,
    made one after the other, work side by side from the start).

    A thread (:func:`prefetch`) shares the interpreter lock with the consumer, so work made of
    many small tensor operations hardly overlaps with a consumer that is made of them too; a
    process does not share it. Where the platform forks (Linux, as PyTorch's data loader
    workers do), the process starts at once with the caller's memory; elsewhere ``source`` and
    ``args`` are pickled into a fresh interpreter (``spawn``, a few seconds), so ``source``
    must be a module-level function. The items come back pickled. The process runs
    ``threads`` torch threads; it may start processes of its own only where it is not a
    ``daemon`` (it is ended with the generator either way).

    An exception raised by ``source`` is raised here in place of the item it stopped, after
    the items before it; a process that dies without one raises :class:`RuntimeError`.
    Closing the returned generator (or leaving a loop over it) ends the process.
    """
    import multiprocessing

    if depth < 1:
        raise ValueError(f"prefetch_process: depth must be >= 1, got {depth}")
    ctx = multiprocessing.get_context("fork" if sys.platform.startswith("linux") else "spawn")
    ready = ctx.Queue(maxsize=depth)
    work = (source, args, ready, threads, os.getpid())
    proc = ctx.Process(target=_serve, args=work, name="torchfit-prefetch", daemon=daemon)
    items = _received(proc, ready)
    next(items)  # the process starts now, not at the first item asked for
    return items


def _received(proc, ready) -> Iterator:
    """The consumer side of :func:`prefetch_process`: starts ``proc`` and yields None, then
    the items it puts on ``ready``; closing it ends the process."""
    proc.start()
    try:
        yield None
        while True:
            try:
                kind, item = ready.get(timeout=_POLL_S)
            except queue.Empty:
                if not proc.is_alive():
                    raise RuntimeError(
                        f"prefetch: the worker process ended with exit code {proc.exitcode}"
                    ) from None
                continue
            if kind == "end":
                return
            if kind == "error":
                raise pickle.loads(item)
            yield pickle.loads(item)
    finally:
        proc.terminate()
        proc.join()
