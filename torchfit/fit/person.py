"""The person side of the fit: contours, distance maps and uncertain pixels of B subjects.

Pixels are ``(u, v)``, pixel (0, 0) the centre of the top-left pixel; distances in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchfit.camera import Camera
from torchfit.errors import ShapeError
from torchfit.image.contours import (
    contour_normals,
    on_image_frame,
    outline_mask,
    trace_outer_contour,
)
from torchfit.image.distance import distance_map

__all__ = ["PersonData", "person_data_from_masks"]


@dataclass
class PersonData:
    """The fixed person side of B subjects, J fitted postures each.

    Attributes:
        contours: J tensors (B, C_j, 2) of person contour pixels (u, v), padded.
        valid: J bool tensors (B, C_j).
        distance_maps: J tensors (B, H, W): D_P, pixels to the person's contour (finite),
            float32 whatever the contours' dtype (the distance transforms compute them in
            float32; :func:`torchfit.image.sample_distance_map` reads them in the
            points' dtype, so a float64 copy would only double their memory).
        camera: B cameras.
        uncertain: optional J bool tensors (B, H, W): pixels where the silhouette is not to be
            trusted (those the segmentation's shadow test removed). A model contour point on
            such a pixel does not count in e_M, and ``valid`` already excludes the person
            contour pixels next to them (see :func:`person_data_from_masks`).
        silhouettes: optional posture index -> (B, H, W) bool silhouettes, for the postures
            whose bent joints the fit marks (:class:`torchfit.fit.bends.BendFit`); only the
            host reads them, and :meth:`to` leaves them where they are.
        normals: optional J tensors (B, C_j, 2), float32: the outward unit normal of each
            person contour pixel (:func:`torchfit.image.contours.contour_normals`; zero on
            padding), for a contour choice that pairs pixels with model samples facing the
            same way (``FitOptions.contour_orientation_px``).
    """

    contours: list[torch.Tensor]
    valid: list[torch.Tensor]
    distance_maps: list[torch.Tensor]
    camera: Camera
    uncertain: list[torch.Tensor] | None = None
    silhouettes: dict[int, torch.Tensor] | None = None
    normals: list[torch.Tensor] | None = None

    @property
    def batch_size(self) -> int:
        """The number of subjects B."""
        return self.camera.batch_size

    @property
    def contour_lengths(self) -> list[int]:
        """The padded person contour length ``C_j`` of every posture."""
        return [v.shape[1] for v in self.valid]

    def to(self, device: torch.device | str) -> PersonData:
        """The same data on ``device`` (the camera too); unchanged where it is there."""
        if all(c.device == torch.device(device) for c in self.contours):
            return self
        return PersonData(
            [c.to(device) for c in self.contours],
            [v.to(device) for v in self.valid],
            [d.to(device) for d in self.distance_maps],
            self.camera.to(device=device),
            None if self.uncertain is None else [u.to(device) for u in self.uncertain],
            self.silhouettes,  # read on the host only (the limbs' crossings), so kept there
            None if self.normals is None else [n.to(device) for n in self.normals],
        )

    def subset(self, index: list[int] | torch.Tensor) -> PersonData:
        """The same data for the subjects ``index`` (padding kept)."""
        idx = torch.as_tensor(index, dtype=torch.long)
        return PersonData(
            [c[idx] for c in self.contours],
            [v[idx] for v in self.valid],
            [d[idx] for d in self.distance_maps],
            self.camera[idx],
            None if self.uncertain is None else [u[idx] for u in self.uncertain],
            None
            if self.silhouettes is None
            else {k: m[idx.to(m.device)] for k, m in self.silhouettes.items()},
            None if self.normals is None else [n[idx] for n in self.normals],
        )


def person_data_from_masks(
    masks: torch.Tensor,
    camera: Camera,
    method: str = "chamfer",
    stride: int = 1,
    dtype: torch.dtype = torch.float64,
    uncertain: torch.Tensor | None = None,
    margin_px: int = 2,
    crop_margin_px: int | None = None,
    normals: bool = False,
) -> PersonData:
    """Person contours and distance maps from silhouettes.

    Args:
        masks: (B, J, H, W) bool silhouettes, J poses per subject.
        camera: B cameras.
        method: distance transform, ``"chamfer"`` (the paper's 3-4) or ``"euclidean"``.
        stride: keep every ``stride``-th contour pixel.
        dtype: dtype of the contours (the distance maps are float32).
        uncertain: optional (B, J, H, W) bool, pixels where the silhouette is not to be
            trusted (:attr:`torchfit.image.SegmentationResult.shadow`): person contour
            pixels within ``margin_px`` of one do not count in e_P, and model contour points
            on one do not count in e_M. A silhouette cut short where a foot or shin looked
            like its own shadow then neither pulls the model's feet up nor pushes the model
            back (the floor contact would turn that into a taller body).
        margin_px: see ``uncertain``.
        crop_margin_px: compute each row's distance map on the box around its own
            silhouette, grown by this many pixels, instead of the whole image (None: the
            whole image); a row's map does not depend on the other rows.
            Inside the box the map is exact (every contour pixel is in it, and the distance
            between two pixels of a box does not leave it); outside, a pixel takes the box
            edge's value plus its Euclidean distance to the box, a bound that keeps growing
            away from the person. For a tracker, whose model stays near the silhouette.
        normals: also give each contour pixel's outward normal (:attr:`PersonData.normals`),
            from the whole traced outline before ``stride`` thins it.

    Returns:
        :class:`PersonData`; an empty silhouette gives an empty contour and a map of large
        constant distance (that pose then only constrains through e_M).

    A silhouette cut by the image frame (a hand or the feet outside the picture) has outline
    pixels along the frame that are the picture's edge, not the person's: they do not count in
    e_P and are not D_P's seeds, so the model is free to reach beyond the frame where the
    person does (its contour points outside the image do not count in e_M either,
    :func:`torchfit.fit.model_contour.select_contour`).
    """
    b, n_pose, h, w = masks.shape
    near = None
    if uncertain is not None:
        if uncertain.shape != masks.shape:
            raise ShapeError(
                f"uncertain: expected the shape of masks {tuple(masks.shape)}, "
                f"got {tuple(uncertain.shape)}"
            )
        k_size = 2 * margin_px + 1
        near = torch.nn.functional.max_pool2d(
            uncertain.float(), k_size, stride=1, padding=margin_px
        ).bool()
    contours, valid, maps, outward = [], [], [], []
    for k in range(n_pose):
        outlines = [trace_outer_contour(masks[i, k]) for i in range(b)]
        traced = [c[::stride] for c in outlines]
        n = max(1, max(len(c) for c in traced))
        pts = torch.zeros(b, n, 2, dtype=dtype)
        ok = torch.zeros(b, n, dtype=torch.bool)
        for i, c in enumerate(traced):
            pts[i, : len(c)] = c.to(dtype)
            ok[i, : len(c)] = ~on_image_frame(c, w, h)
            if near is not None and len(c):
                c = c.long()
                ok[i, : len(c)] &= ~near[i, k, c[:, 1], c[:, 0]]
        contours.append(pts)
        valid.append(ok)
        if normals:
            nrm = torch.zeros(b, n, 2, dtype=torch.float32)
            for i, c in enumerate(outlines):
                along = contour_normals(c)[::stride]
                nrm[i, : len(along)] = along
            outward.append(nrm)
        # D_P's seeds are the traced outlines (what mask_to_distance_map would trace again)
        # less the image frame's pixels
        inner = [c[~on_image_frame(c, w, h)] for c in outlines]
        seeds = outline_mask(inner, h, w, masks.device)
        if crop_margin_px is None:
            dmap = distance_map(seeds, method)[:, 0]
        else:
            dmap = _cropped_distance_map(masks[:, k], seeds, method, crop_margin_px)
        maps.append(torch.nan_to_num(dmap, posinf=float(h + w)))
    flags = None if uncertain is None else [uncertain[:, k] for k in range(n_pose)]
    return PersonData(contours, valid, maps, camera, flags, None, outward if normals else None)


def _cropped_distance_map(
    masks: torch.Tensor, seeds: torch.Tensor, method: str, margin: int
) -> torch.Tensor:
    """(B, H, W) distance maps to the (B, 1, H, W) ``seeds`` (the outlines of the silhouettes
    ``masks``), each exact on its own silhouette's box grown by ``margin`` and bounded outside
    it (see :func:`person_data_from_masks`, ``crop_margin_px``).

    The transform runs once on the rows' common box, where every map is exact; then each row
    outside its own box takes its own box edge's value plus the distance to it, so a row's map
    is the one it would get alone."""
    b, h, w = masks.shape
    boxes = []
    for i in range(b):
        rows = masks[i].any(1).nonzero().flatten()
        cols = masks[i].any(0).nonzero().flatten()
        if rows.numel():
            y0, y1 = max(int(rows[0]) - margin, 0), min(int(rows[-1]) + margin, h - 1)
            x0, x1 = max(int(cols[0]) - margin, 0), min(int(cols[-1]) + margin, w - 1)
            boxes.append((y0, y1, x0, x1))
        else:  # no silhouette: the whole image, as without a crop
            boxes.append((0, h - 1, 0, w - 1))
    y0, y1 = min(bx[0] for bx in boxes), max(bx[1] for bx in boxes)
    x0, x1 = min(bx[2] for bx in boxes), max(bx[3] for bx in boxes)
    crop = distance_map(seeds[..., y0 : y1 + 1, x0 : x1 + 1], method)[:, 0]
    v = torch.arange(h, device=masks.device)
    u = torch.arange(w, device=masks.device)
    out = crop.new_empty(b, h, w)
    for i, (r0, r1, c0, c1) in enumerate(boxes):
        # the nearest pixel of the row's own box, and the distance to it
        vc, uc = v.clamp(r0, r1), u.clamp(c0, c1)
        dv, du = (v - vc).to(crop.dtype), (u - uc).to(crop.dtype)
        edge = crop[i].index_select(0, vc - y0).index_select(1, uc - x0)
        out[i] = edge + (dv[:, None] ** 2 + du[None, :] ** 2).sqrt()
    return out
