"""The contour choice's worker processes: the same choice as in the fit's own process."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from torchfit.body.model import BodyModel
from torchfit.config.schema import RunConfig
from torchfit.errors import ConfigError
from torchfit.fit import contour_pool
from torchfit.fit.model_contour import EdgeSampler, select_contours
from torchfit.image import pack_mask, unpack_mask
from torchfit.pipeline.runtime import contour_workers_for

SIZE = (160, 200)


@pytest.fixture
def workers():
    """Two contour workers for the test, none after it."""
    contour_pool.set_contour_workers(2)
    yield 2
    contour_pool.set_contour_workers(0)


def _images(n: int, seed: int):
    """The template's mesh seen from n cameras (orthographic, turned about the vertical),
    and a noisy ring of person contour pixels per image with some padding."""
    model = BodyModel("mpeg4_full")
    v = model(**model.zeros(1)).vertices[0]  # (V, 3), metres
    g = torch.Generator().manual_seed(seed)
    pixels, contours = [], []
    for _ in range(n):
        a = float(torch.rand(1, generator=g)) * 6.28
        x = v[:, 0] * np.cos(a) + v[:, 2] * np.sin(a)
        px = torch.stack([80 + 90 * x, 190 - 90 * v[:, 1]], 1)
        pixels.append(px + 0.3 * torch.randn(px.shape, generator=g, dtype=px.dtype))
        t = torch.linspace(0, 6.28, 120, dtype=torch.float64)
        contours.append(torch.stack([80 + 30 * t.cos(), 100 + 80 * t.sin()], 1))
    valid = torch.ones(n, 120, dtype=torch.bool)
    valid[:, 100:] = False
    return model, torch.stack(pixels).double(), torch.stack(contours), valid


def _same(a, b) -> None:
    assert torch.equal(a.samples, b.samples)
    assert torch.equal(a.sample_valid, b.sample_valid)
    assert torch.equal(a.nearest, b.nearest)
    assert len(a.silhouettes) == len(b.silhouettes)
    assert all(np.array_equal(a.mask(i), b.mask(i)) for i in range(len(a.silhouettes)))


def test_workers_choose_exactly_what_the_process_itself_chooses(workers):
    model, pix, contours, valid = _images(7, seed=3)
    sampler = EdgeSampler(model.faces, 4)
    # two "postures": 4 and 3 images
    args = ([pix[:4], pix[4:]], [contours[:4], contours[4:]], [valid[:4], valid[4:]])
    pooled = select_contours(sampler, *args, SIZE, 1.0)
    contour_pool.set_contour_workers(0)
    alone = select_contours(sampler, *args, SIZE, 1.0)
    assert [s.samples.shape[0] for s in pooled] == [4, 3]
    for a, b in zip(pooled, alone, strict=True):
        _same(a, b)
    # the meshes are in view: every image has a contour and nearest samples
    assert all(bool(s.sample_valid.any(1).all()) for s in alone)
    assert all(bool((s.nearest[:, :100] > 0).any()) for s in alone)


def test_packed_silhouettes_come_back_unchanged():
    g = np.random.default_rng(0)
    mask = np.zeros((50, 70), np.uint8)
    mask[10:31, 5:44] = 255 * (g.random((21, 39)) > 0.5)
    for m in (mask, np.zeros((50, 70), np.uint8), np.full((50, 70), 255, np.uint8)):
        back = unpack_mask(pickle.loads(pickle.dumps(pack_mask(m))))
        assert back.dtype == np.uint8 and np.array_equal(back, m)


def test_the_edge_sampler_pickles_as_arrays():
    model = BodyModel("mpeg4_simple")
    s = EdgeSampler(model.faces, 3)
    state = s.__getstate__()
    assert not any(torch.is_tensor(v) for v in state.values())
    back = pickle.loads(pickle.dumps(s))
    for key in ("edges", "edge_faces", "faces", "t"):
        assert torch.equal(getattr(back, key), getattr(s, key))
    assert back.k == 3


def test_contour_workers_setting():
    assert contour_workers_for(RunConfig()) == 0  # the CPU: the fit's own process
    assert contour_workers_for(RunConfig(device="cuda"), cores=8) == 7
    assert contour_workers_for(RunConfig(device="cuda"), cores=1) == 0
    assert contour_workers_for(RunConfig(device="cuda", contour_workers=3), cores=8) == 3
    assert contour_workers_for(RunConfig(contour_workers=2)) == 2
    with pytest.raises(ConfigError, match="run.contour_workers"):
        RunConfig(contour_workers=-1)
    with pytest.raises(ValueError, match="contour workers"):
        contour_pool.set_contour_workers(-2)


def test_a_killed_worker_costs_one_call_its_speed_not_its_result(workers, caplog):
    import os
    import signal

    model, pix, contours, valid = _images(4, seed=5)
    sampler = EdgeSampler(model.faces, 4)
    args = ([pix], [contours], [valid])
    first = select_contours(sampler, *args, SIZE, 1.0)[0]
    pids = list(contour_pool._pool._processes)
    assert len(pids) >= 1
    for pid in pids:
        os.kill(pid, signal.SIGKILL)
    with caplog.at_level("WARNING", logger="torchfit.fit.contour_pool"):
        again = select_contours(sampler, *args, SIZE, 1.0)[0]
    assert "contour worker process died" in caplog.text
    _same(again, first)
    assert contour_pool._pool is None
    # the next call starts a new pool, with the same result
    _same(select_contours(sampler, *args, SIZE, 1.0)[0], first)
    assert contour_pool._pool is not None
    assert not set(contour_pool._pool._processes) & set(pids)


def test_workers_start_ahead_of_the_first_choice(workers):
    futures = contour_pool.start_contour_workers()
    assert len(futures) == 2 and all(f.result(timeout=120) for f in futures)
    assert len(contour_pool._pool._processes) == 2
    contour_pool.set_contour_workers(0)
    assert contour_pool._pool is None and contour_pool.start_contour_workers() == []


def test_workers_that_keep_dying_are_given_up(workers, caplog):
    import os
    import signal

    model, pix, contours, valid = _images(3, seed=7)
    sampler = EdgeSampler(model.faces, 4)
    args = ([pix], [contours], [valid])
    alone = None
    for _ in range(contour_pool.MAX_BROKEN):
        select_contours(sampler, *args, SIZE, 1.0)  # makes a pool
        for pid in list(contour_pool._pool._processes):
            os.kill(pid, signal.SIGKILL)
        with caplog.at_level("WARNING", logger="torchfit.fit.contour_pool"):
            alone = select_contours(sampler, *args, SIZE, 1.0)[0]
    assert "contour worker processes died twice" in caplog.text
    assert "__main__" in caplog.text
    assert contour_pool.contour_workers() == 0 and contour_pool._pool is None
    contour_pool.set_contour_workers(0)
    _same(select_contours(sampler, *args, SIZE, 1.0)[0], alone)
