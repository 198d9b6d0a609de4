"""Compute an iterator's next items in a background thread (:func:`prefetch`).

The tracker reads and segments frame ``t + 1`` while it fits frame ``t``: the image decoding
and the segmentation's tensor work release the GIL, so on a machine with a spare core the two
overlap and a frame costs about the larger of the two instead of their sum.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from typing import TypeVar

__all__ = ["prefetch"]

T = TypeVar("T")
_END = object()
_POLL_S = 0.1


class _Raised:
    """An exception of the source, carried to the consumer in its place."""

    def __init__(self, error: BaseException) -> None:
        self.error = error


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
        while not stop.is_set():
            try:
                ready.put(item, timeout=_POLL_S)
                return True
            except queue.Full:
                continue
        return False

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
