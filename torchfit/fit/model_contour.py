"""The model's outer contour as a differentiable function of the projected mesh.

Which mesh points form the outer contour of the model silhouette is a discrete choice, made
outside autograd each time the parameters change (:func:`select_contour`):

1. every mesh edge carries ``K`` sample points at fixed fractions ``t_k = (k + 0.5) / K``;
2. candidate edges are the projected silhouette edges: between a front- and a back-facing
   triangle, or on the border of a segment mesh;
3. the candidate edges are drawn as lines and the outer outline of the drawing traced (the
   outer boundary of a projected mesh runs along its silhouette edges:
   :func:`torchfit.viz.raster.edge_outline`); a candidate sample lies *on the model contour*
   when it is within ``tolerance`` pixels of an outline pixel;
4. for every person contour pixel the nearest selected sample is recorded; with an
   orientation weight ``λ`` (pixels), the nearest in ``(u, v, λ n)``, ``n`` the outward
   normals of the pixel and of the sample's projected edge: a sample facing the other way
   counts ``2 λ`` pixels further off, so that the outline of an arm that the model holds
   against the trunk is not paired with the side of the person's trunk beside it.

Given that choice (:func:`contour_endpoints` turns it into mesh edges and fractions), the
contour points and :func:`point_to_edge_distance` are plain torch functions of the projected
vertices, so the residuals built on them differentiate with autograd. Pixels: ``(u, v)``,
pixel (0, 0) the centre of the top-left pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torchfit.errors import ShapeError, check_shape
from torchfit.fit.contour_geometry import near_boundary, outward_normals
from torchfit.fit.contour_pool import map_chunks
from torchfit.image.contours import on_image_frame
from torchfit.viz.raster import edge_outline, fixed_points, render_fixed

__all__ = [
    "EdgeSampler",
    "ContourSelection",
    "ContourEndpoints",
    "select_contour",
    "select_contours",
    "contour_endpoints",
    "point_to_edge_distance",
]


class EdgeSampler:
    """Sample points on the unique edges of a triangle mesh.

    Args:
        faces: (F, 3) triangle vertex indices.
        samples_per_edge: K samples per edge at ``t_k = (k + 0.5) / K``.
    """

    def __init__(self, faces: torch.Tensor, samples_per_edge: int = 4) -> None:
        if samples_per_edge < 1:
            raise ShapeError(f"samples_per_edge: expected >= 1, got {samples_per_edge}")
        f = faces.cpu().long()
        edges = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]).sort(dim=1).values
        self.edges, inverse = torch.unique(edges, dim=0, return_inverse=True)  # (E, 2)
        # the (up to) two faces on each edge, -1 where an edge borders one face only
        face_of = torch.arange(f.shape[0]).repeat(3)
        order = torch.argsort(inverse, stable=True)
        first = torch.full((self.edges.shape[0],), -1, dtype=torch.long)
        second = torch.full((self.edges.shape[0],), -1, dtype=torch.long)
        inv_sorted, faces_sorted = inverse[order], face_of[order]
        starts = torch.ones_like(inv_sorted, dtype=torch.bool)
        starts[1:] = inv_sorted[1:] != inv_sorted[:-1]
        first[inv_sorted[starts]] = faces_sorted[starts]
        follow = torch.zeros_like(starts)
        follow[1:] = starts[:-1] & ~starts[1:]
        second[inv_sorted[follow]] = faces_sorted[follow]
        self.edge_faces = torch.stack([first, second], 1)  # (E, 2)
        self.k = samples_per_edge
        self.t = (torch.arange(samples_per_edge, dtype=torch.float64) + 0.5) / samples_per_edge
        self.faces = f

    def __getstate__(self) -> dict:
        # as arrays: a tensor pickles through shared memory between processes
        return {k: v.numpy() if torch.is_tensor(v) else v for k, v in self.__dict__.items()}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(
            {k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v for k, v in state.items()}
        )

    @property
    def num_samples(self) -> int:
        """Number of contour candidates (edges x samples per edge)."""
        return self.edges.shape[0] * self.k

    def endpoints(self, sample_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Vertex indices (a, b) of samples: each (...,) (their fraction: :meth:`fraction`)."""
        e = sample_index // self.k
        return self.edges[e, 0], self.edges[e, 1]

    def fraction(self, sample_index: torch.Tensor) -> torch.Tensor:
        """Fractions t along their edges of samples (N,) -> (N,)."""
        return self.t[sample_index % self.k]

    def silhouette_edges(self, pixels: np.ndarray) -> np.ndarray:
        """(V, 2) projected vertices of one mesh -> (E,) bool: edges between a front- and a
        back-facing triangle, or on the border of the mesh (candidates for the contour)."""
        tri = pixels[self.faces.numpy()]
        a, b = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        facing = (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]) > 0
        ef = self.edge_faces.numpy()
        border = ef[:, 1] < 0
        return border | (facing[ef[:, 0]] != facing[np.maximum(ef[:, 1], 0)])

    def all_points(self, pixels: torch.Tensor, edges: torch.Tensor | None = None) -> torch.Tensor:
        """(B, V, 2) projected vertices -> (B, n*K, 2) sample points of the edges ``edges``
        (n,) (default: all of them, n = E), in :meth:`sample_index` order."""
        e = self.edges if edges is None else self.edges[edges]
        a = pixels[:, e[:, 0]]  # (B, n, 2)
        b = pixels[:, e[:, 1]]
        t = self.t.to(pixels)[None, None, :, None]
        pts = a[:, :, None] * (1 - t) + b[:, :, None] * t  # (B, n, K, 2)
        return pts.reshape(pixels.shape[0], -1, 2)

    def sample_index(self, edges: np.ndarray) -> np.ndarray:
        """(n,) edge indices -> the (n*K,) indices of their samples."""
        return (edges[:, None] * self.k + np.arange(self.k)).reshape(-1)


@dataclass
class ContourSelection:
    """The discrete contour choice for a batch of projected meshes (one image each).

    Attributes:
        samples: (B, N) sample indices on the model contour, padded with 0.
        sample_valid: (B, N) bool, False on padding.
        nearest: (B, C) for each person contour pixel, the position (into ``samples``' second
            dimension) of its nearest selected sample; 0 where invalid.
        silhouettes: what draws the B model silhouettes: per image its projected vertices in
            fixed point (:func:`torchfit.viz.raster.fixed_points`), the mesh's triangles and
            the image size; :meth:`mask` renders one (for overlays, the bent joints' marks and
            tests), the choice itself does not need them.
        marks: optional (B, L, 3) pixel targets ``(u, v, valid)`` of the posture's marked
            joints, made with the choice (:class:`torchfit.fit.bends.BendFit`).
    """

    samples: torch.Tensor
    sample_valid: torch.Tensor
    nearest: torch.Tensor
    silhouettes: list[tuple]
    marks: torch.Tensor | None = None

    def mask(self, i: int) -> np.ndarray:
        """The (H, W) uint8 silhouette of image ``i``: 255 inside, 0 outside."""
        return render_fixed(*self.silhouettes[i])

    def repeat_interleave(self, repeats: int) -> ContourSelection:
        """The same choice for every row of a batch folded ``repeats`` times (row b*r + i)."""
        rep = lambda x: x.repeat_interleave(repeats, dim=0)  # noqa: E731
        sil = [m for m in self.silhouettes for _ in range(repeats)]
        marks = None if self.marks is None else rep(self.marks)
        return ContourSelection(
            rep(self.samples), rep(self.sample_valid), rep(self.nearest), sil, marks
        )

    def take(self, rows: torch.Tensor) -> ContourSelection:
        """The choice of the images ``rows`` (N,), in that order (padding kept)."""
        at = rows.to(self.samples.device)
        sil = [self.silhouettes[i] for i in rows.tolist()]
        marks = None if self.marks is None else self.marks[at]
        return ContourSelection(
            self.samples[at], self.sample_valid[at], self.nearest[at], sil, marks
        )

    def put(self, rows: torch.Tensor, other: ContourSelection) -> ContourSelection:
        """This choice with the images ``rows`` (N,) replaced by ``other``'s N images.

        The sample padding is widened to the wider of the two; what a residual makes of a
        choice does not depend on its padding.
        """
        width = max(self.samples.shape[1], other.samples.shape[1])
        at = rows.to(self.samples.device)
        sil = list(self.silhouettes)
        for i, packed in zip(rows.tolist(), other.silhouettes, strict=True):
            sil[i] = packed
        marks = self.marks
        if other.marks is not None:
            base = (
                self.marks
                if self.marks is not None
                else other.marks.new_zeros(self.samples.shape[0], *other.marks.shape[1:])
            )
            marks = base.index_copy(0, at, other.marks)
        return ContourSelection(
            _widen(self.samples, width).index_copy(0, at, _widen(other.samples, width)),
            _widen(self.sample_valid, width).index_copy(0, at, _widen(other.sample_valid, width)),
            self.nearest.index_copy(0, at, other.nearest),
            sil,
            marks,
        )


def _widen(t: torch.Tensor, width: int) -> torch.Tensor:
    """(B, n) padded with zeros (False) on the right to (B, width)."""
    if t.shape[1] == width:
        return t
    return torch.cat([t, t.new_zeros(t.shape[0], width - t.shape[1])], 1)


@torch.no_grad()
def select_contour(
    sampler: EdgeSampler,
    pixels: torch.Tensor,
    person_contours: torch.Tensor,
    person_valid: torch.Tensor,
    image_size: tuple[int, int],
    tolerance: float = 1.0,
    person_normals: torch.Tensor | None = None,
    orientation_px: float | torch.Tensor = 0.0,
) -> ContourSelection:
    """Choose the mesh edge samples that form the model's outer contour.

    Args:
        sampler: edge samples of the model mesh.
        pixels: (B, V, 2) projected vertices.
        person_contours: (B, C, 2) person contour pixels, padded.
        person_valid: (B, C) bool.
        image_size: ``(width, height)``.
        tolerance: max distance in pixels from a contour pixel of the rendered silhouette.
        person_normals: optional (B, C, 2) outward normals of the person contour pixels
            (:attr:`torchfit.fit.PersonData.normals`), for ``orientation_px``.
        orientation_px: ``λ`` of the module docstring, one for all images or a (B,) tensor
            (0, or no ``person_normals``: the nearest sample whichever way it faces).

    Returns:
        :class:`ContourSelection`. An image whose model has no contour sample in view gets no
        valid sample (the residual turns that into a large constant, see
        :func:`torchfit.fit.residuals.model_to_person` and ``NO_CONTOUR_PENALTY``). Samples
        outside the image are not chosen, nor are those near the image frame only because the
        rendered silhouette runs along it where the model leaves the picture.
    """
    normals = None if person_normals is None else [person_normals]
    return select_contours(
        sampler,
        [pixels],
        [person_contours],
        [person_valid],
        image_size,
        tolerance,
        normals,
        orientation_px,
    )[0]


@torch.no_grad()
def select_contours(
    sampler: EdgeSampler,
    pixels: list[torch.Tensor],
    person_contours: list[torch.Tensor],
    person_valid: list[torch.Tensor],
    image_size: tuple[int, int],
    tolerance: float = 1.0,
    person_normals: list[torch.Tensor] | None = None,
    orientation_px: float | list[torch.Tensor] = 0.0,
) -> list[ContourSelection]:
    """:func:`select_contour` for several batches of images at once (one per posture, say):
    their images are spread over the contour worker processes where there are some
    (:mod:`torchfit.fit.contour_pool`), with the same result.

    Args:
        pixels, person_contours, person_valid: one (B, V, 2), (B, C, 2) and (B, C) each per
            batch of images.
        person_normals: optional, one (B, C, 2) per batch of images (see
            :func:`select_contour`).
        orientation_px: ``λ``, one for all images or one (B,) tensor per batch.
    """
    items = []
    if person_normals is None:
        person_normals = [None] * len(pixels)
    if not isinstance(orientation_px, list):
        orientation_px = [torch.as_tensor(orientation_px).expand(p.shape[0]) for p in pixels]
    batches = zip(
        pixels, person_contours, person_valid, person_normals, orientation_px, strict=True
    )
    for px, contours, valid, normals, lam in batches:
        check_shape("pixels", px, ("B", "V", 2))
        px = px.detach().cpu().double().numpy()
        contours, valid = contours.cpu().numpy(), valid.cpu().numpy()
        normals = None if normals is None else normals.cpu().numpy()
        lam = lam.detach().cpu().double().numpy()
        for i in range(px.shape[0]):
            weighed = normals is not None and lam[i] > 0
            items.append(
                (px[i], contours[i], valid[i], normals[i] if weighed else None, float(lam[i]))
            )
    chosen = map_chunks(_choose, items, (sampler, image_size, tolerance))
    out, at = [], 0
    for px, contours in zip(pixels, person_contours, strict=True):
        out.append(
            _selection(
                chosen[at : at + px.shape[0]], contours.shape[:2], px.device, sampler, image_size
            )
        )
        at += px.shape[0]
    return out


def _choose(item: tuple, sampler: EdgeSampler, size: tuple[int, int], tolerance: float):
    """One image's choice: (its contour samples, the position of the one nearest to each
    person contour pixel (0 where invalid or none), its projected vertices in fixed point)."""
    from scipy.spatial import cKDTree

    px, contour, valid, normals, orientation = item
    w, h = size
    cand = np.flatnonzero(sampler.silhouette_edges(px))
    fixed = fixed_points(px)
    # the outline inside the picture, off its frame (where the frame cuts the model, the
    # picture's edge is not the model's contour)
    bpix = edge_outline(px, sampler.edges.numpy()[cand], sampler.faces.numpy(), (w, h), fixed)
    bpix = bpix[~on_image_frame(bpix, w, h)]
    # the samples of the candidate edges only
    p = sampler.all_points(torch.from_numpy(px)[None], torch.from_numpy(cand))[0].numpy()
    on = sampler.sample_index(cand)
    inside = (p[:, 0] > -0.5) & (p[:, 0] < w - 0.5) & (p[:, 1] > -0.5) & (p[:, 1] < h - 0.5)
    on, p = on[inside], p[inside]
    ui = np.clip(np.rint(p[:, 0]), 0, w - 1).astype(np.int64)
    vi = np.clip(np.rint(p[:, 1]), 0, h - 1).astype(np.int64)
    near = near_boundary(bpix, ui, vi, (w, h), tolerance)
    on, p = on[near], p[near]
    nearest = np.zeros(len(valid), np.int64)
    if len(on) and valid.any():
        query = contour[valid]
        if normals is not None:
            p = np.concatenate([p, orientation * outward_normals(sampler, px, on)], 1)
            query = np.concatenate([query, orientation * normals[valid]], 1)
        nearest[valid] = cKDTree(p).query(query)[1]
    return on, nearest, fixed


def _selection(
    chosen: list, contour_shape, device: torch.device, sampler: EdgeSampler, size
) -> ContourSelection:
    """The :class:`ContourSelection` of a batch's :func:`_choose` results."""
    b = len(chosen)
    n = max(1, max(len(on) for on, _, _ in chosen))
    samples = torch.zeros(b, n, dtype=torch.long)
    sample_valid = torch.zeros(b, n, dtype=torch.bool)
    nearest = torch.zeros(contour_shape, dtype=torch.long)
    for i, (on, near, _) in enumerate(chosen):
        samples[i, : len(on)] = torch.from_numpy(on)
        sample_valid[i, : len(on)] = True
        nearest[i] = torch.from_numpy(near)
    faces = sampler.faces.numpy()
    silhouettes = [(fixed, faces, tuple(size)) for _, _, fixed in chosen]
    return ContourSelection(
        samples.to(device), sample_valid.to(device), nearest.to(device), silhouettes
    )


@dataclass
class ContourEndpoints:
    """Mesh vertices and edge fractions behind a :class:`ContourSelection`.

    Attributes:
        model_a, model_b: (B, N) vertex indices of the edge of each model contour sample.
        model_t: (B, N) the sample's fraction along its edge.
        person_a, person_b, person_t: (B, C) the same for the sample nearest to each person
            contour pixel.
    """

    model_a: torch.Tensor
    model_b: torch.Tensor
    model_t: torch.Tensor
    person_a: torch.Tensor
    person_b: torch.Tensor
    person_t: torch.Tensor

    def vertices(self) -> torch.Tensor:
        """Sorted unique vertex indices used anywhere in the batch."""
        return torch.unique(torch.cat([self.model_a.flatten(), self.model_b.flatten()]))


def contour_endpoints(sampler: EdgeSampler, selection: ContourSelection) -> ContourEndpoints:
    """Resolve a selection into edge endpoints and fractions (all long/float tensors)."""
    dev = selection.samples.device
    samples = selection.samples.cpu()
    nearest = torch.gather(samples, 1, selection.nearest.cpu())
    ma, mb = sampler.endpoints(samples)
    pa, pb = sampler.endpoints(nearest)
    return ContourEndpoints(
        ma.to(dev),
        mb.to(dev),
        sampler.fraction(samples).to(dev),
        pa.to(dev),
        pb.to(dev),
        sampler.fraction(nearest).to(dev),
    )


def point_to_edge_distance(
    x: torch.Tensor, a: torch.Tensor, b: torch.Tensor, t0: torch.Tensor, half: float
) -> torch.Tensor:
    """Distance from points to the piece ``t in [t0 - half, t0 + half]`` of edges a→b.

    The model contour near a chosen sample is the piece of its mesh edge the sample stands
    for; the distance is to that piece, so it is exact for straight contour edges.

    Args:
        x: (..., 2) points; a, b: (..., 2) projected edge endpoints; t0: (...) fractions.
        half: half the spacing of the samples along an edge (``0.5 / K``).

    Returns:
        (...) pixels, smooth at zero distance (``sqrt(d^2 + eps^2) - eps``).
    """
    d = b - a
    t = ((x - a) * d).sum(-1) / (d * d).sum(-1).clamp_min(1e-12)
    t = torch.minimum(torch.maximum(t, t0 - half), t0 + half)
    diff = x - (a + t[..., None] * d)
    eps = 1e-6
    return torch.sqrt((diff * diff).sum(-1) + eps * eps) - eps
