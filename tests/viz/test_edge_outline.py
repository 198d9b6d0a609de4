"""The model's outline drawn from its silhouette edges (torchfit.viz.raster.edge_outline)
against the outline of its filled triangles."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from torchfit.fit.model_contour import EdgeSampler, select_contour
from torchfit.viz.raster import edge_outline, outer_outlines, render_silhouette

SIZE = (160, 120)


def _bodies(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Projected vertices (V, 2) and faces of a few overlapping solids (a torus among them:
    not convex, with a hole) under a random rotation, orthographic, about the image centre."""
    g = np.random.default_rng(seed)
    parts = [
        trimesh.creation.capsule(height=1.2, radius=0.25, count=[10, 10]),
        trimesh.creation.icosphere(subdivisions=2, radius=0.45),
        trimesh.creation.torus(major_radius=0.7, minor_radius=0.15, major_sections=24),
        trimesh.creation.box(extents=(0.3, 1.4, 0.2)),
    ]
    for p in parts:
        p.apply_translation(g.uniform(-0.5, 0.5, 3))
    mesh = trimesh.util.concatenate(parts)
    turn = trimesh.transformations.random_rotation_matrix(g.uniform(size=3))[:3, :3]
    xyz = mesh.vertices @ turn.T
    scale, centre = g.uniform(30, 45), np.array(SIZE) / 2 + g.uniform(-10, 10, 2)
    return xyz[:, :2] * scale + centre, np.asarray(mesh.faces)


def _filled_outline(pixels: np.ndarray, faces: np.ndarray) -> np.ndarray:
    return np.concatenate(outer_outlines(render_silhouette(pixels, faces, SIZE))).astype(np.int64)


def _apart(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance (in pixels, max-norm) from a pixel of ``a`` to the nearest of ``b``."""
    return float(np.abs(a[:, None] - b[None]).max(-1).min(1).max())


def _silhouette_edges(pixels: np.ndarray, faces: np.ndarray) -> np.ndarray:
    sampler = EdgeSampler(torch.from_numpy(faces), 1)
    return sampler.edges.numpy()[sampler.silhouette_edges(pixels)]


@pytest.mark.parametrize("seed", range(6))
def test_the_edges_outline_is_the_filled_silhouettes_within_a_pixel(seed):
    pixels, faces = _bodies(seed)
    edges = _silhouette_edges(pixels, faces)
    drawn, filled = edge_outline(pixels, edges, faces, SIZE), _filled_outline(pixels, faces)
    assert len(drawn) > 100
    # the two rasterisations part by at most a pixel, both ways: no silhouette edge inside
    # the body (the torus's hole, an occluded part) is taken for its outline
    assert _apart(drawn, filled) <= 1 and _apart(filled, drawn) <= 1
    # without the triangles filled: the outline would have been much the same drawn either way
    assert not np.array_equal(drawn, filled)


@pytest.mark.parametrize("shift", [(0.0, 55.0), (-70.0, 0.0), (0.0, 0.0)])
def test_a_body_the_frame_cuts_is_outlined_as_its_filled_silhouette(shift):
    pixels, faces = _bodies(0)
    pixels = pixels + np.array(shift)
    if shift == (0.0, 0.0):  # far larger than the image
        pixels = (pixels - np.array(SIZE) / 2) * 40 + np.array(SIZE) / 2
    edges = _silhouette_edges(pixels, faces)
    # the gaps the frame opens between the parts are outside, as in the filled silhouette;
    # the outline runs along the frame there (the contour choice leaves those pixels out)
    assert np.array_equal(edge_outline(pixels, edges, faces, SIZE), _filled_outline(pixels, faces))
    assert edge_outline(pixels, edges[:0], faces, SIZE).shape == (0, 2)


def test_the_selections_silhouette_is_the_filled_render():
    pixels, faces = _bodies(4)
    sampler = EdgeSampler(torch.from_numpy(faces), 2)
    px = torch.from_numpy(pixels)[None]
    person = torch.full((1, 5, 2), 60.0, dtype=torch.float64)
    sel = select_contour(sampler, px, person, torch.ones(1, 5, dtype=torch.bool), SIZE, 1.0)
    assert np.array_equal(sel.mask(0), render_silhouette(pixels, faces, SIZE))
    assert int(sel.sample_valid.sum()) > 50
