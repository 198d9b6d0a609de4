"""A tracked frame's second silhouette, and which rows take it.

Light trousers before a light wall are an attenuated copy of it: the shadow test takes them for
the wall's shadow and the silhouette ends at the hips, the shoes cut off below. The reader
segments such a frame a second time with the pixels between the body and the part cut off
below given back (:meth:`torchfit.pipeline.sequence.SequenceSegmenter.segmented`,
``track.bridge_min``). A shadow on the floor between the feet is given back the same way, so
the tracker decides per row (:func:`torchfit.track.track`): the second silhouette where the
predicted pose draws the body over what it adds (:func:`expected`), else where a solve to it,
from the predicted pose or from it with the legs at their neutral angles (a leg hidden behind
the other), explains it better than the solve to the first (the body model tells which one is
a person; in a stretch of refused frames those solves are tried every
:data:`SECOND_TRIAL_EVERY`-th).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import torch

from torchfit.body.model import BodyModel
from torchfit.camera import Camera, project_points, stack_cameras
from torchfit.fit.person import PersonData
from torchfit.track.options import PoseLayout, TrackOptions
from torchfit.viz.raster import render_silhouette

__all__ = [
    "FrameSilhouettes",
    "expected",
    "joined",
    "placed",
    "SECOND_INSIDE",
    "SECOND_MARGIN_PX",
    "SECOND_BETTER",
    "SECOND_TRIAL_EVERY",
]

#: the predicted pose expects a second silhouette where at least this fraction of the pixels
#: it adds lie on the pose's silhouette grown by :data:`SECOND_MARGIN_PX`
SECOND_INSIDE = 0.5
SECOND_MARGIN_PX = 3
#: a solve to a second silhouette is taken where its contour RMS is below this many times the
#: first's (not on a tie: a second silhouette whose additions the contour never reaches, a
#: blob apart from the body, explains the frame as well to the last digits)
SECOND_BETTER = 0.99
#: in a stretch of frames whose second silhouette was refused, the solve to it is made every
#: this many frames (a frame of the stretch looks like the one before; each solve costs a
#: frame's tracking time)
SECOND_TRIAL_EVERY = 4


@dataclass
class FrameSilhouettes:
    """One frame of B sequences with a second silhouette for some of them.

    Attributes:
        person: the person data (:func:`torchfit.track.frame_data`) of the first silhouettes.
        masks: (B, H, W) the first silhouettes.
        second: (B, H, W) the second ones (a row without one holds its first).
        has: (B,) bool, the rows with a second silhouette.
        second_person: the :func:`torchfit.track.frame_data` of ``second``, where the caller
            made it ahead (the reader does); None: made here when a row takes it.
    """

    person: PersonData
    masks: torch.Tensor
    second: torch.Tensor
    has: torch.Tensor
    second_person: PersonData | None = None

    def second_data(self, cameras: Camera, options: TrackOptions, dtype: torch.dtype) -> PersonData:
        """The person data of the second silhouettes (made once)."""
        from torchfit.track.tracker import frame_data

        if self.second_person is None:
            self.second_person = frame_data(self.second, cameras, options, dtype)
        return self.second_person

    def chosen(
        self, rows: list[bool], cameras: Camera, options: TrackOptions, dtype: torch.dtype
    ) -> PersonData:
        """The person data with the second silhouette in the rows ``rows`` (B,): a row's
        data do not depend on the other rows' (its distance map is its own, the contours'
        padding counts nowhere), so they are taken row by row from the two."""
        if not any(rows):
            return self.person
        second = self.second_data(cameras, options, dtype)
        if all(r or not bool(h) for r, h in zip(rows, self.has, strict=True)):
            return second  # a row without a second silhouette has the same data in both
        take = torch.tensor(rows).nonzero().flatten()
        return placed(self.person, take, second.subset(take))


def _widening(*parts: PersonData):
    """Pads a (B, C, ...) tensor of one posture's contours to the widest of the parts'."""
    width = max(p.contours[0].shape[1] for p in parts)

    def wide(t: torch.Tensor) -> torch.Tensor:
        pad = [0, 0] * (t.dim() - 2) + [0, width - t.shape[1]]
        return torch.nn.functional.pad(t, pad)

    return wide


def joined(*parts: PersonData) -> PersonData:
    """Person data (one posture) with the rows of each part in turn (contours padded to the
    widest; a row's data do not depend on the others')."""
    wide = _widening(*parts)
    return PersonData(
        [torch.cat([wide(p.contours[0]) for p in parts])],
        [torch.cat([wide(p.valid[0]) for p in parts])],
        [torch.cat([p.distance_maps[0] for p in parts])],
        stack_cameras([p.camera for p in parts]),
    )


def placed(first: PersonData, rows: torch.Tensor, other: PersonData) -> PersonData:
    """Person data (one posture): ``first``'s with its rows ``rows`` (n,) replaced by the n
    rows of ``other`` (contours padded to the wider of the two; a row's data do not depend on
    the others')."""
    wide = _widening(first, other)
    at = rows.to(first.contours[0].device)
    return PersonData(
        [wide(first.contours[0]).index_copy(0, at, wide(other.contours[0]))],
        [wide(first.valid[0]).index_copy(0, at, wide(other.valid[0]))],
        [first.distance_maps[0].index_copy(0, at, other.distance_maps[0])],
        first.camera,
    )


def expected(
    model: BodyModel,
    scales: torch.Tensor,
    cameras: Camera,
    pred: torch.Tensor,
    frame: FrameSilhouettes,
) -> list[bool]:
    """Per row (B,), whether the pose row ``pred`` (B, P) draws the body over what the row's
    second silhouette adds to its first (:data:`SECOND_INSIDE`)."""
    rows = torch.nonzero(frame.has).flatten()
    out = [False] * frame.masks.shape[0]
    if not rows.numel():
        return out
    t, r, q = PoseLayout.split(pred[rows])
    with torch.no_grad():
        pix = project_points(model(scales[rows], q, t, r).vertices, cameras[rows])
    faces = model.faces.numpy()
    k = 2 * SECOND_MARGIN_PX + 1
    grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    for j, i in enumerate(rows.tolist()):
        drawn = render_silhouette(pix[j].cpu().numpy(), faces, cameras.image_size)
        near = torch.from_numpy(cv2.dilate(drawn, grow) > 0)
        added = frame.second[i] & ~frame.masks[i]
        n = int(added.sum())
        out[i] = n > 0 and int((added & near).sum()) >= SECOND_INSIDE * n
    return out
