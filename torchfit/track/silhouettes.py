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
from torchfit.camera import Camera, project_points
from torchfit.fit.person import PersonData
from torchfit.track.options import PoseLayout, TrackOptions
from torchfit.viz.raster import render_silhouette

__all__ = [
    "FrameSilhouettes",
    "expected",
    "SECOND_INSIDE",
    "SECOND_MARGIN_PX",
    "SECOND_TRIAL_EVERY",
]

#: the predicted pose expects a second silhouette where at least this fraction of the pixels
#: it adds lie on the pose's silhouette grown by :data:`SECOND_MARGIN_PX`
SECOND_INSIDE = 0.5
SECOND_MARGIN_PX = 3
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
    """

    person: PersonData
    masks: torch.Tensor
    second: torch.Tensor
    has: torch.Tensor

    def chosen(
        self, rows: list[bool], cameras: Camera, options: TrackOptions, dtype: torch.dtype
    ) -> PersonData:
        """The person data with the second silhouette in the rows ``rows`` (B,)."""
        from torchfit.track.tracker import frame_data

        if not any(rows):
            return self.person
        masks = self.masks.clone()
        pick = torch.tensor(rows)
        masks[pick] = self.second[pick]
        return frame_data(masks, cameras, options, dtype)


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
