"""Poser.world_jacobian: the closed-form derivatives of the posed, floor-standing vertices of a
posture w.r.t. the fit's parameters (group scales, the posture's joints, the Euler root and
the floor translation, through the floor contact) against central differences of
Poser.world."""

from __future__ import annotations

import pytest
import torch

from torchfit.fit.layout import ParamLayout
from torchfit.fit.pose import Poser, template_layout


def _poser(model) -> tuple[Poser, ParamLayout]:
    layout = template_layout(model, [1, 2, 3, 4, 5, 6])
    centres = torch.tensor([[0.3, -3.5, 1.3], [-0.4, -3.0, 1.6]], dtype=torch.float64)
    return Poser(model, layout, centres), layout


@pytest.mark.parametrize("posture", [1, 3, 5])
def test_world_jacobian_matches_central_differences(model, posture):
    poser, layout = _poser(model)
    g = torch.Generator().manual_seed(posture)
    x = layout.initial(dtype=torch.float64).expand(2, -1).clone()
    x = x + 0.05 * torch.randn(x.shape, generator=g, dtype=torch.float64)
    rows = torch.tensor([0, 1])
    index = torch.randperm(model.template.vertices.shape[0], generator=g)[:250]
    world, d_world = poser.world_jacobian(x, posture, rows, index)
    torch.testing.assert_close(world, poser.world(x, posture, rows, index)[0], rtol=0, atol=1e-12)
    cols = poser.columns(posture)
    assert d_world.shape == (2, 250, 3, cols.numel())
    h = 1e-6
    for i, c in enumerate(cols.tolist()):
        plus, minus = x.clone(), x.clone()
        plus[:, c] += h
        minus[:, c] -= h
        fd = (
            poser.world(plus, posture, rows, index)[0] - poser.world(minus, posture, rows, index)[0]
        )
        torch.testing.assert_close(d_world[..., i], fd / (2 * h), atol=1e-7, rtol=0)


def test_floor_contact_at_a_tie_takes_the_mean_of_both_soles(model):
    """At the template start both soles touch the floor at once (a symmetric body, no tilt):
    the floor's derivative is then the mean of the two soles', as forward-mode AD of
    torch.minimum gives it, and the one-sided differences bracket it."""
    poser, layout = _poser(model)
    x = layout.initial(dtype=torch.float64).expand(2, -1).clone()
    soles = torch.tensor(poser.soles)
    z = poser.world(x, 1, torch.tensor([0, 1]), soles)[0][..., 2]
    assert torch.equal(z[:, 0], z[:, 1])  # a true tie
    index = torch.arange(0, model.template.vertices.shape[0], 7)
    _, d_world = poser.world_jacobian(x, 1, torch.tensor([0, 1]), index)
    roll = poser.columns(1).tolist().index(layout.blocks[1].root_column("roll"))
    h = 1e-6
    plus, minus = x.clone(), x.clone()
    plus[:, layout.blocks[1].root_column("roll")] += h
    minus[:, layout.blocks[1].root_column("roll")] -= h
    rows = torch.tensor([0, 1])
    at = poser.world(x, 1, rows, index)[0]
    up = (poser.world(plus, 1, rows, index)[0] - at) / h
    down = (at - poser.world(minus, 1, rows, index)[0]) / h
    assert float((up - down).abs().max()) > 1e-3  # a kink: the lower sole changes
    torch.testing.assert_close(d_world[..., roll], 0.5 * (up + down), atol=1e-6, rtol=0)


def test_world_postures_is_world_of_each_posture_bitwise(model):
    """The contour choice poses the six postures in one model call; each posture's vertices
    are bit for bit those of its own call (the rows of a model call are independent)."""
    poser, layout = _poser(model)
    g = torch.Generator().manual_seed(7)
    x = layout.initial(dtype=torch.float64).expand(2, -1).clone()
    x = x + 0.05 * torch.randn(x.shape, generator=g, dtype=torch.float64)
    rows = torch.tensor([1, 0])
    together = poser.world_postures(x, [1, 2, 3, 4, 5, 6], rows)
    assert len(together) == 6
    for j, verts in zip([1, 2, 3, 4, 5, 6], together, strict=True):
        assert torch.equal(verts, poser.world(x, j, rows)[0])
