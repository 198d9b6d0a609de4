"""torchfit.io.prefetch: items in order, errors in place, the thread works ahead and stops."""

from __future__ import annotations

import threading

import pytest

from torchfit.io.prefetch import prefetch


def _prefetch_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "torchfit-prefetch" and t.is_alive()]


def test_items_come_in_order_and_the_thread_ends():
    assert list(prefetch(iter(range(50)), depth=3)) == list(range(50))
    assert _prefetch_threads() == []


def test_an_error_is_raised_after_the_items_before_it():
    def source():
        yield 1
        yield 2
        raise ValueError("frame 3 is unreadable")

    got = []
    with pytest.raises(ValueError, match="frame 3 is unreadable"):
        for item in prefetch(source()):
            got.append(item)
    assert got == [1, 2]
    assert _prefetch_threads() == []


def test_the_next_item_is_made_while_the_consumer_works():
    started_second = threading.Event()

    def source():
        yield "first"
        started_second.set()
        yield "second"

    items = prefetch(source(), depth=1)
    assert next(items) == "first"
    # the consumer has not asked for the second item; the thread has started on it anyway
    assert started_second.wait(timeout=30)
    assert list(items) == ["second"]


def test_closing_early_stops_the_thread():
    made = []

    def endless():
        n = 0
        while True:
            made.append(n)
            yield n
            n += 1

    items = prefetch(endless(), depth=2)
    assert [next(items) for _ in range(3)] == [0, 1, 2]
    items.close()
    assert _prefetch_threads() == []
    # the thread stopped after at most the items the queue could hold and the one in hand
    assert len(made) <= 3 + 2 + 1


def test_depth_zero_runs_in_the_caller_and_negative_is_an_error():
    assert list(prefetch(iter("abc"), depth=0)) == ["a", "b", "c"]
    with pytest.raises(ValueError, match="depth must be >= 0"):
        list(prefetch(iter("abc"), depth=-1))
