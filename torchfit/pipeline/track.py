"""Motion capture runs: a fitted model, sequences of frames, the tracker, the outputs.

:func:`track_sequences` reads B sequences (each ``camera.yaml``, ``background/``,
``frames/``, optionally ``masks/`` and ``truth.json``: :mod:`torchfit.pipeline.sequence`),
turns every frame into a silhouette (``segmentation.method``), tracks them together
(:func:`torchfit.track.track`, one frame per batch row) and writes per sequence into its
output folder: ``joints_world.json`` (``{"fps", "frames": [{joint: [x, y, z]}, …]}``,
design.md's joints, world frame, metres), ``motion.bvh`` (the fitted skeleton, one rotation
set per frame), ``track.csv`` (frame, status, cost, iterations, ms, contour_rms, confidence),
TensorBoard scalars under ``tb/``, and with a truth, ``eval.json`` (mean per-joint position
error, head_top excluded).

The first frame starts from pose hypotheses solved together, the best contour kept
(:func:`torchfit.track.start_poses`): the person must face the camera, roughly, in the first
frame; after that the temporal term keeps the side.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from torchfit.body.bvh import model_motion
from torchfit.body.model import BodyModel
from torchfit.camera import (
    project_points,
    stack_cameras,
)
from torchfit.config.schema import SilhouetteSource
from torchfit.errors import DataError, SegmentationError, SequenceError
from torchfit.image import pack_mask, unpack_mask
from torchfit.io.bvh import write_bvh
from torchfit.io.export import write_json
from torchfit.io.files import make_dirs, write_atomic
from torchfit.io.images import write_image
from torchfit.io.prefetch import prefetch, prefetch_process
from torchfit.io.video import VideoWriter
from torchfit.measurements import JOINT_NAMES
from torchfit.pipeline.sequence import Sequence, SequenceSegmenter, load_sequence
from torchfit.pipeline.track_truth import joint_errors, skeleton_scales
from torchfit.track import PoseLayout, TrackOptions, frame_data, start_poses, track
from torchfit.track.silhouettes import FrameSilhouettes, placed

__all__ = [
    "TrackConfig",
    "Sequence",
    "FittedModel",
    "load_fitted",
    "load_sequence",
    "track_sequences",
    "joint_errors",
    "skeleton_scales",
]


@dataclass
class TrackConfig:
    """configs/track.yaml: the segmentation (with where the silhouettes come from,
    ``segmentation.method``) and the tracker's options."""

    segmentation: SilhouetteSource = field(default_factory=SilhouetteSource)
    track: TrackOptions = field(default_factory=TrackOptions)


class FittedModel(NamedTuple):
    """What tracking reads of a fitted subject folder's ``params.json``.

    Attributes:
        template: the template's name.
        scales: segment name -> its (3,) scales.
        status: the fit's status (``ok`` where the file names none): a ``poor_fit`` model
            tracks with segment lengths the fit did not trust.
        message: the fit's reasons for that status.
    """

    template: str
    scales: dict
    status: str
    message: str


def load_fitted(folder: str | Path) -> FittedModel:
    """The template, segment scales and status of a fitted subject folder (params.json).

    Raises:
        DataError: no or unreadable params.json.
    """
    path = Path(folder) / "params.json"
    if not path.is_file():
        raise DataError(f"fitted model not found: {path} (expected a fit's subject folder)")
    try:
        doc = json.loads(path.read_text())
        scales = doc["segment_scales"]
        template = doc["template"]
    except (ValueError, KeyError) as exc:
        raise DataError(f"{path}: not a fit's params.json ({exc})") from None
    return FittedModel(template, scales, str(doc.get("status", "ok")), str(doc.get("message", "")))


def _row_masks(seqs: list[Sequence], segmenters: list[SequenceSegmenter], n: int, ids: list[int]):
    """For ``n`` frames, the rows' (silhouette, second silhouette or None) of these sequences
    (:meth:`SequenceSegmenter.segmented`); a finished sequence repeats its last frame.

    Raises:
        SequenceError: a sequence that cannot be read or segmented, with its ``ids`` entry
            (its position among all the sequences tracked).
    """
    sources = [g.segmented() for g in segmenters]
    last: list[tuple | None] = [None] * len(seqs)
    for f in range(n):
        for i, s in enumerate(seqs):
            if f < s.num_frames:
                try:
                    last[i] = next(sources[i])
                except (DataError, SegmentationError) as exc:
                    raise SequenceError(ids[i], str(exc)) from None
        yield list(last)


def _masks(seqs: list[Sequence], segmenters: list[SequenceSegmenter], readers: int = 1):
    """Per frame, (B, H, W) silhouettes and the rows' second silhouettes (a list, None where a
    row has none); a finished sequence repeats its last frame. With ``readers`` > 1 (at most
    one a sequence) the sequences are split into that many groups of rows, each read and
    segmented in a process of its own (one torch thread each): a sequence's silhouettes do
    not depend on the others, so they are the same either way."""
    n = max(s.num_frames for s in seqs)
    if readers <= 1:
        groups = [_row_masks(seqs, segmenters, n, list(range(len(seqs))))]
    else:
        parts = [p.tolist() for p in np.array_split(np.arange(len(seqs)), readers)]
        groups = [
            prefetch_process(
                _row_masks, [seqs[i] for i in p], [segmenters[i] for i in p], n, p, threads=1
            )
            for p in parts
        ]
    try:
        for rows in zip(*groups, strict=True):
            flat = [r for g in rows for r in g]
            yield torch.stack([m for m, _ in flat]), [second for _, second in flat]
    finally:
        for g in groups:
            g.close()


def _frames(
    seqs, segmenters, cameras, config: TrackConfig, dtype, keep: bool = False, readers: int = 1
):
    """Per frame, what the tracker fits: the person data (a :class:`FrameSilhouettes` where a
    row has a second silhouette), with the silhouettes (B, H, W) they were made from: the
    first frame's as they are (its start needs them); the others' packed (:func:`_pack`,
    with the rows' second ones) where ``keep`` (the overlays draw them), else None (they would
    be sent for nothing)."""
    for f, (masks, seconds) in enumerate(_masks(seqs, segmenters, readers)):
        person = frame_data(masks, cameras, config.track, dtype)
        kept = masks if f == 0 else (_pack(masks) if keep else None)
        if any(s is not None for s in seconds):
            has = torch.tensor([s is not None for s in seconds])
            second = torch.stack(
                [m if s is None else s for m, s in zip(masks, seconds, strict=True)]
            )
            # made here, ahead, for the rows that have one (the others' are their first's)
            rows = has.nonzero().flatten()
            extra = frame_data(second[rows], cameras[rows], config.track, dtype)
            if len(rows) < len(has):
                extra = placed(person, rows, extra)
            person = FrameSilhouettes(person, masks, second, has, extra)
            if keep and f > 0:
                kept = (kept, _pack_seconds(person))
        yield kept, person


def _pack_seconds(frame: FrameSilhouettes) -> list[tuple | None]:
    """Per row, its second silhouette packed as :func:`_pack` packs (None for a row without
    one): what the overlays draw for a frame tracked to it."""
    return [
        pack_mask(m.numpy()) if h else None for m, h in zip(frame.second, frame.has, strict=True)
    ]


def _pack(masks: torch.Tensor) -> list[tuple]:
    """(B, H, W) silhouettes -> per row :func:`~torchfit.image.morphology.pack_mask`'s bounding
    box and bits (a few KB a frame where a whole mask is 52 KB at 720x576: the overlays of long
    sequences keep every frame's)."""
    return [pack_mask(m) for m in masks.numpy()]


def _joints(model: BodyModel, scales: torch.Tensor, x: torch.Tensor) -> dict[str, np.ndarray]:
    t, r, q = PoseLayout.split(x)
    with torch.no_grad():
        out = model(scales.expand(x.shape[0], -1, -1), q, t, r)
        named = model.joint_positions(out)
    return {n: named[n].cpu().numpy() for n in JOINT_NAMES}


def track_sequences(
    model: BodyModel,
    scales: torch.Tensor,
    sequences: list[Sequence],
    outs: list[Path],
    config: TrackConfig,
    tb=None,
    progress=None,
    overlays: bool = False,
    ahead: str = "thread",
    start: torch.Tensor | None = None,
    readers: int = 1,
) -> list[dict]:
    """Track ``sequences`` together and write each one's outputs to ``outs``.

    Args:
        model: the body model (template of the fit).
        scales: (B, S, 3) or (S, 3) the fitted scales (per sequence or shared).
        sequences: B sequences.
        outs: B output folders.
        config: segmentation and tracker options.
        tb: optional :class:`torchfit.pipeline.tensorboard.TensorBoardCallback`.
        progress: wraps the frame iterator.
        overlays: also write ``overlay/<frame>.png`` (model contour green, person magenta)
            and the same frames as ``overlay.avi`` (Motion JPEG at the sequence's rate).
        ahead: where the next frames are read, segmented and turned into contours and
            distance maps while one is tracked: ``"thread"``, ``"process"`` (a second
            interpreter: it starts in a few seconds, and then overlaps with the tracking far
            better than a thread, which shares the interpreter lock) or ``"none"``.
        start: (B, P) pose rows (:class:`torchfit.track.PoseLayout`) the first frames are
            tracked from, where the caller knows them; None: solved from the first frames'
            silhouettes (:func:`torchfit.track.start_poses`).
        readers: processes that read and segment the frames, each for a group of the
            sequences (1: one, where ``ahead`` says); the contours and distance maps are made
            where ``ahead`` says. Reading and segmenting a 720x576 frame takes about 30 ms,
            tracking a row of many about 10: with many sequences one reader is the bound. The
            tracks are the same for any number.

    Returns:
        Per sequence a summary (frames, statuses, ms per frame, errors with a truth).

    Raises:
        SequenceError: a sequence that cannot be read or segmented (its position in
            ``sequences``), before any output is written; tracked without it, the others
            give what they give alone.
    """
    b = len(sequences)
    if scales.dim() == 2:
        scales = scales[None].expand(b, -1, -1)
    scales = scales.to(model.dtype).contiguous()
    cameras = stack_cameras([s.camera for s in sequences]).to(dtype=model.dtype)
    segmenters = [
        SequenceSegmenter(s, config.segmentation, config.track.bridge_min) for s in sequences
    ]
    layout = PoseLayout(model, config.track)
    if start is not None and tuple(start.shape) != (b, layout.num_params):
        raise ValueError(
            f"start: expected ({b}, {layout.num_params}) pose rows, got {tuple(start.shape)}"
        )
    # the next frames are read, segmented and turned into contours and distance maps while
    # this one is tracked
    readers = max(1, min(readers, b))  # at most one a sequence
    args = (sequences, segmenters, cameras, config, model.dtype, overlays, readers)
    if ahead == "process":
        # a process that starts the readers' processes is not a daemon
        ahead = prefetch_process(_frames, *args, daemon=readers == 1)
    elif ahead in ("thread", "none"):
        ahead = prefetch(_frames(*args), depth=2 if ahead == "thread" else 0)
    else:
        raise ValueError(f"ahead: expected 'thread', 'process' or 'none', got {ahead!r}")
    first, first_person = next(ahead)
    if start is None:
        plain = first_person.person if isinstance(first_person, FrameSilhouettes) else first_person
        start = start_poses(model, scales, cameras, first, layout, config.track, plain)
    start = start.to(model.dtype)

    # per frame, the silhouettes the overlays draw (with the rows' second ones where any)
    kept = []
    if overlays:
        kept.append(_pack(first))
        if isinstance(first_person, FrameSilhouettes):
            kept[0] = (kept[0], _pack_seconds(first_person))

    def frames_again():
        yield first_person
        for masks, person in ahead:
            if overlays:
                kept.append(masks)
            yield person

    records = track(model, scales, cameras, frames_again(), start, config.track, progress)
    summaries = []
    for i, (s, out) in enumerate(zip(sequences, outs, strict=True)):
        recs = records[i][: s.num_frames]
        make_dirs(out)
        x = torch.stack([r.x for r in recs])
        joints = _joints(model, scales[i], x)
        frames_doc = [
            {n: [round(float(v), 5) for v in joints[n][f]] for n in JOINT_NAMES}
            for f in range(len(recs))
        ]
        write_json(out / "joints_world.json", {"fps": s.fps, "frames": frames_doc})
        t, r, q = PoseLayout.split(x)
        write_bvh(out / "motion.bvh", model_motion(model, scales[i], q, t, r, 1.0 / s.fps))
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(
            ["frame", "status", "cost", "iterations", "ms", "contour_rms", "confidence", "bridged"]
        )
        for rec in recs:
            w.writerow(
                [
                    rec.frame,
                    rec.status,
                    f"{rec.cost:.4f}",
                    rec.iterations,
                    f"{rec.ms:.1f}",
                    f"{rec.contour_rms:.3f}",
                    f"{rec.confidence:.3f}",
                    int(rec.bridged),
                ]
            )
        write_atomic(out / "track.csv", buf.getvalue())
        if overlays:
            people = [
                (k[1][i] if rec.bridged else k[0][i]) if isinstance(k, tuple) else k[i]
                for k, rec in zip(kept, recs, strict=False)
            ]
            _write_overlays(model, scales[i], s, people, x, recs, out)
        if tb is not None:
            for rec in recs:
                tb.add_scalar(f"track/{s.name}/contour_rms", rec.contour_rms, rec.frame)
                tb.add_scalar(f"track/{s.name}/confidence", rec.confidence, rec.frame)
                tb.add_scalar(f"track/{s.name}/iterations", rec.iterations, rec.frame)
        summary = {
            "sequence": s.name,
            "frames": len(recs),
            "status": {
                k: sum(r.status == k for r in recs) for k in ("ok", "recovered", "uncertain")
            },
            "ms_per_frame": float(np.mean([r.ms for r in recs])),
            "median_confidence": float(np.median([r.confidence for r in recs])),
            # frames tracked to their second silhouette (light legs given back)
            "bridged_frames": sum(r.bridged for r in recs),
        }
        if s.truth is not None:
            summary.update(joint_errors(frames_doc, s.truth[: len(recs)], s.camera))
            write_json(out / "eval.json", summary)
        summaries.append(summary)
    return summaries


def _write_overlays(model, scales, seq, people, x, recs, out) -> None:
    """``overlay/`` and ``overlay.avi`` of one sequence: its frames, the tracked model's
    contour and the person's silhouettes ``people`` (per frame, packed by :func:`_pack`) that
    it was tracked to."""
    from torchfit.viz.overlay import fit_overlay
    from torchfit.viz.raster import render_silhouette

    cam = seq.camera.to(dtype=model.dtype)
    t, r, q = PoseLayout.split(x)
    with torch.no_grad():
        verts = model(scales.expand(x.shape[0], -1, -1), q, t, r).vertices
    faces = model.faces.numpy()
    with VideoWriter(out / "overlay.avi", seq.fps) as video:
        for f, (rec, image, packed) in enumerate(zip(recs, seq.images(), people, strict=False)):
            person = unpack_mask(packed) > 0
            pix = project_points(verts[f : f + 1], cam)[0].numpy()
            mask = render_silhouette(pix, faces, seq.camera.image_size) > 0
            rgb = (image[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            label = f"{seq.name} {f:06d} {rec.status} {rec.contour_rms:.1f}px"
            frame = fit_overlay(rgb, person, mask, label)
            write_image(out / "overlay" / f"{f:06d}.png", frame)
            video.write(frame)
