"""Fixtures of the solver tests."""

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_thread():
    """One torch thread: the solver tests time nothing, and two threads on a shared 2-core
    machine cost milliseconds per small tensor operation."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
