"""The TensorBoard callback writes real event files (read back with EventAccumulator)."""

from __future__ import annotations

import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from torchfit.errors import TorchfitError
from torchfit.pipeline.tensorboard import TensorBoardCallback
from torchfit.solver import LMOptions, levenberg_marquardt

T = torch.linspace(0.0, 3.0, 12, dtype=torch.float64)


def residual(x):
    return x[:, :1] * torch.exp(-x[:, 1:2] * T) - 2.0 * torch.exp(-1.3 * T)


def test_event_files_hold_per_problem_scalars(tmp_path):
    records = []
    x0 = torch.tensor([[1.0, 1.0], [3.0, 0.4]], dtype=torch.float64)
    with TensorBoardCallback(tmp_path, "fit", problem_names=["alice", "bob"]) as tb:

        def both(it):
            records.append(it)
            return tb(it)

        res = levenberg_marquardt(residual, x0, LMOptions(max_iter=30), callback=both)
    assert list(tmp_path.glob("events.out.tfevents.*"))
    acc = EventAccumulator(str(tmp_path))
    acc.Reload()
    tags = set(acc.Tags()["scalars"])
    for name in ("alice", "bob"):
        assert {f"fit/{name}/cost", f"fit/{name}/damping", f"fit/{name}/step_norm"} <= tags
    for b, name in enumerate(("alice", "bob")):
        events = acc.Scalars(f"fit/{name}/cost")
        # One event per iteration the problem ran (it stops being logged once finished).
        assert [e.step for e in events] == list(range(1, int(res.n_iter[b]) + 1))
        expected = [float(r.cost[b]) for r in records[: len(events)]]
        assert [e.value for e in events] == pytest.approx(expected, rel=1e-6)
        damping = acc.Scalars(f"fit/{name}/damping")
        assert damping[0].value == pytest.approx(float(records[0].damping[b]), rel=1e-6)


def test_bad_arguments():
    with pytest.raises(TorchfitError, match="log_dir: expected a path or a SummaryWriter"):
        TensorBoardCallback(3)


def test_wrong_number_of_names(tmp_path):
    tb = TensorBoardCallback(tmp_path, problem_names=["only_one"])
    x0 = torch.ones(2, 2, dtype=torch.float64)
    with pytest.raises(TorchfitError, match=r"problem_names: expected 2 names"):
        levenberg_marquardt(residual, x0, callback=tb)
    tb.close()
