"""torchfit.io.prefetch: items in order, errors in place, the thread or the process works ahead
and stops."""

from __future__ import annotations

import multiprocessing
import os
import threading
import time

import pytest
import torch

from torchfit.io.prefetch import prefetch, prefetch_process


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


# ---- in a second process --------------------------------------------------------------------


def _squares(n: int):
    import os

    for i in range(n):
        yield i * i, os.getpid()


def _broken():
    yield torch.ones(3)
    raise ValueError("frame 2 is unreadable")


class _Unpicklable(Exception):
    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.handle = lambda: None  # a lambda does not pickle


def _broken_badly():
    yield 1
    raise _Unpicklable("the camera went away")


def _endless(flag_path: str):
    n = 0
    while True:
        with open(flag_path, "a") as f:
            f.write(f"{n}\n")
        yield n
        n += 1


def test_a_process_yields_the_items_in_order_from_another_process():
    items = list(prefetch_process(_squares, 20, depth=2))
    assert [v for v, _ in items] == [i * i for i in range(20)]
    assert {pid for _, pid in items} != {os.getpid()}
    assert multiprocessing.active_children() == []


def _items_before(source, error: type, match: str) -> list:
    """The items a process yields before ``source`` raises (which must come out as ``error``);
    no worker is left."""
    got = []
    with pytest.raises(error, match=match):
        for item in prefetch_process(source):
            got.append(item)
    assert multiprocessing.active_children() == []
    return got


def test_a_process_hands_tensors_and_errors_back():
    got = _items_before(_broken, ValueError, "frame 2 is unreadable")
    assert len(got) == 1 and torch.equal(got[0], torch.ones(3))


def test_an_error_that_does_not_pickle_still_says_what_happened():
    assert _items_before(_broken_badly, RuntimeError, "_Unpicklable: the camera went away") == [1]


def test_closing_early_ends_the_process(tmp_path):
    flag = tmp_path / "made.txt"
    items = prefetch_process(_endless, str(flag), depth=2)
    assert [next(items) for _ in range(3)] == [0, 1, 2]
    items.close()
    assert multiprocessing.active_children() == []
    made = len(flag.read_text().split())
    time.sleep(0.3)
    assert len(flag.read_text().split()) == made  # nothing runs any more
    with pytest.raises(ValueError, match="depth must be >= 1"):
        next(prefetch_process(_squares, 3, depth=0))


def _mark(path: str):
    with open(path, "w") as f:
        f.write("started")
    yield 1


def test_each_process_starts_when_made_not_when_first_asked(tmp_path):
    """Several readers made one after the other work side by side from the start (each
    sequence's background model is made there before its first frame)."""
    flags = [tmp_path / f"{k}.txt" for k in range(2)]
    items = [prefetch_process(_mark, str(f)) for f in flags]
    deadline = time.time() + 30
    while not all(f.exists() for f in flags) and time.time() < deadline:
        time.sleep(0.05)
    assert all(f.exists() for f in flags)  # before any item was asked for
    assert [list(i) for i in items] == [[1], [1]]
    never = prefetch_process(_endless, str(tmp_path / "never.txt"), depth=1)
    never.close()  # closed before its first item: the process ends all the same
    assert multiprocessing.active_children() == []


def test_the_process_exits_when_its_consumer_is_killed(tmp_path):
    """A consumer killed outright (no chance to close the generator) leaves no worker behind:
    the worker, blocked on a full queue with items larger than the pipe holds, sees its
    parent gone and exits without waiting to hand them over."""
    import signal
    import subprocess
    import sys

    pid_file = tmp_path / "worker.pid"
    script = f"""
import os, sys, time
sys.path.insert(0, {str(os.getcwd())!r})
from torchfit.io.prefetch import prefetch_process

def endless(path):
    with open(path, "w") as f:
        f.write(str(os.getpid()))
    while True:
        yield bytes(1 << 20)  # more than the pipe holds: the worker's writer blocks

items = prefetch_process(endless, {str(pid_file)!r}, depth=1)
next(items)
print("ready", flush=True)
time.sleep(60)
"""
    consumer = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert consumer.stdout.readline().strip() == "ready"
        worker = int(pid_file.read_text())
        os.kill(consumer.pid, signal.SIGKILL)
        consumer.wait(timeout=10)
        deadline = time.time() + 10
        while time.time() < deadline:
            try:
                os.kill(worker, 0)
            except ProcessLookupError:
                break
            time.sleep(0.1)
        else:
            os.kill(worker, signal.SIGKILL)
            pytest.fail("the worker outlived its killed consumer by 10 s")
    finally:
        consumer.kill()
