"""Guided capture from a video: the background frames, and one frame per posture.

The video starts with the empty scene; the person then walks onto the mark and strikes the
six postures of design.md section 4 in order, holding each still for about a second.

1. **Background:** the frames from the start until the first one that differs from the first
   frames (more than ``changed_fraction`` of the pixels by more than ``change_level``); at
   least :data:`~torchfit.io.dataset.MIN_BACKGROUND_FRAMES` of them.
2. **Segmentation** of every later frame against them (:func:`torchfit.image.segment`).
3. **Still stretches:** runs of at least ``min_still`` frames whose silhouettes each differ
   from the previous one by less than ``still_change`` of their area (symmetric difference).
4. **Templates:** posture k's template body at its nominal angles, facing the camera on the
   mark (:func:`torchfit.body.postures.pose_nominal`), scaled to ``height_m`` (or the
   template's own height), projected with the camera. Before comparing, the template's
   silhouette is scaled about its foot point (the lowest row, the column centroid) to the
   frame's silhouette height (not when ``height_m`` is given) and moved so that the two foot
   points coincide.
5. **Matching:** the score of a frame for posture k is the intersection over union of the two
   silhouettes; each posture takes the best frame of one still stretch, the stretches in the
   postures' order (a dynamic programme over the stretches maximises the total score), and
   a posture whose best score is below ``min_score`` is not found.
6. **Held frames:** a held posture's frames differ by sensor noise alone. With
   ``hold_frames`` > 1 the posture image is the per-pixel median of up to ``hold_frames``
   frames around the chosen one (:func:`held_frames`: contiguous in time, inside its still
   stretch, each silhouette's intersection over union with the chosen frame's at least
   ``hold_iou``); 1 keeps the chosen frame alone. The background frames need no such
   step: the segmentation's background model is fitted to all of them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from torchfit.body.measure import measure_model
from torchfit.body.model import BodyModel
from torchfit.body.postures import pose_nominal
from torchfit.camera import Camera, project_points
from torchfit.errors import DataError
from torchfit.image.background import fit_background
from torchfit.image.plausibility import cut_borders
from torchfit.image.segment import SegmentationOptions, segment
from torchfit.io.dataset import MIN_BACKGROUND_FRAMES, N_POSES
from torchfit.viz.raster import render_silhouette

__all__ = [
    "CaptureOptions",
    "CaptureResult",
    "empty_start",
    "still_stretches",
    "template_silhouettes",
    "match_score",
    "choose_frames",
    "held_frames",
    "median_frame",
    "capture_from_frames",
]


@dataclass(frozen=True)
class CaptureOptions:
    """The knobs of :func:`capture_from_frames` (see the module docstring)."""

    change_level: float = 0.1  # a pixel changed: a channel moved by more than this (in [0, 1])
    changed_fraction: float = 0.002  # a frame is no longer empty above this share of pixels
    still_change: float = 0.03  # symmetric difference / area between consecutive silhouettes
    min_still: int = 3  # frames
    min_score: float = 0.5  # intersection over union
    max_background: int = 10  # background frames kept (the first ones)
    hold_frames: int = 1  # frames combined (per-pixel median) per posture image
    hold_iou: float = 0.97  # a combined frame's silhouette IoU with the chosen frame's

    def __post_init__(self) -> None:
        if self.hold_frames < 1:
            raise ValueError(f"hold_frames must be >= 1, got {self.hold_frames}")
        if not 0.0 < self.hold_iou <= 1.0:
            raise ValueError(f"hold_iou must be in (0, 1], got {self.hold_iou}")


@dataclass
class CaptureResult:
    """What :func:`capture_from_frames` chose.

    Attributes:
        background: indices of the background frames.
        chosen: posture number -> frame index (found postures only).
        scores: posture number -> best score (found or not).
        stretches: the still stretches ``(first, last)`` (frame indices).
        missing: the posture numbers not found.
        combined: posture number -> the frames whose median is its image (ascending; the
            chosen frame alone with ``hold_frames`` 1).
        cut: posture number -> the image borders that cut the chosen frame's silhouette
            (empty when the person is inside the picture); the fit flags such a posture.
    """

    background: list[int]
    chosen: dict[int, int] = field(default_factory=dict)
    combined: dict[int, list[int]] = field(default_factory=dict)
    scores: dict[int, float] = field(default_factory=dict)
    stretches: list[tuple[int, int]] = field(default_factory=list)
    missing: list[int] = field(default_factory=list)
    cut: dict[int, list[str]] = field(default_factory=dict)


def _float(frames: torch.Tensor) -> torch.Tensor:
    """Frames as float in [0, 1] (uint8 frames are divided by 255)."""
    if frames.dtype == torch.uint8:
        return frames.float().div_(255.0)
    return frames


def empty_start(frames: torch.Tensor, options: CaptureOptions) -> int:
    """How many frames at the start show the empty scene (frames (N, 3, H, W), uint8 or in
    [0, 1])."""
    reference = _float(frames[:MIN_BACKGROUND_FRAMES]).median(0).values
    for i in range(frames.shape[0]):
        changed = (_float(frames[i]) - reference).abs().amax(0) > options.change_level
        if float(changed.float().mean()) > options.changed_fraction:
            return i
    return frames.shape[0]


def still_stretches(
    masks: torch.Tensor, first: int, options: CaptureOptions
) -> list[tuple[int, int]]:
    """Runs ``(a, b)`` (inclusive frame indices, offset by ``first``) of still silhouettes
    (masks (N, H, W) bool, an empty one never still)."""
    n = masks.shape[0]
    still = [False] * n
    for i in range(1, n):
        area = float(masks[i].sum())
        if area == 0:
            continue
        change = float((masks[i] ^ masks[i - 1]).sum()) / area
        still[i] = change < options.still_change
    runs, i = [], 0
    while i < n:
        if still[i]:
            j = i
            while j + 1 < n and still[j + 1]:
                j += 1
            a = i - 1  # the frame before the first still one belongs to the stretch
            if j - a + 1 >= options.min_still:
                runs.append((first + a, first + j))
            i = j + 1
        else:
            i += 1
    return runs


def template_silhouettes(
    model: BodyModel, camera: Camera, height_m: float | None = None
) -> np.ndarray:
    """(6, H, W) bool: the six postures' template silhouettes seen by ``camera`` (B = 1),
    the template scaled uniformly to ``height_m`` (its own height when None)."""
    scales = torch.ones(1, model.num_segments, 3, dtype=model.dtype)
    if height_m is not None:
        own = float(measure_model(model, scales)["height_m"][0])
        scales = scales * (height_m / own)
    cam = camera.to(dtype=model.dtype)
    faces = model.faces.cpu().numpy()
    out = []
    for k in range(1, N_POSES + 1):
        _, posed = pose_nominal(model, scales, k, cam.centre)
        px = project_points(posed.vertices, cam)[0].detach().cpu().numpy()
        out.append(render_silhouette(px, faces, camera.image_size) > 0)
    return np.stack(out)


def _foot_and_height(mask: np.ndarray) -> tuple[float, float, float] | None:
    rows = np.nonzero(mask.any(1))[0]
    if rows.size == 0:
        return None
    top, bottom = rows[0], rows[-1]
    # across: the silhouette's column centroid (the feet's columns move with a foot a few
    # pixels higher than the other, e.g. in the straddle)
    return float(np.nonzero(mask)[1].mean()), float(bottom), float(bottom - top + 1)


def match_score(mask: np.ndarray, template: np.ndarray, rescale: bool = True) -> float:
    """Intersection over union of a silhouette and a template silhouette (both (H, W) bool),
    the template moved so that the foot points (the lowest row, the column centroid)
    coincide and, with ``rescale``, scaled about its foot point to the silhouette's
    height."""
    a, b = _foot_and_height(mask), _foot_and_height(template)
    if a is None or b is None:
        return 0.0
    s = a[2] / b[2] if rescale else 1.0
    M = np.array([[s, 0.0, a[0] - s * b[0]], [0.0, s, a[1] - s * b[1]]])
    h, w = mask.shape
    moved = cv2.warpAffine(template.astype(np.uint8), M, (w, h), flags=cv2.INTER_NEAREST) > 0
    union = float((moved | mask).sum())
    return float((moved & mask).sum()) / union if union else 0.0


def choose_frames(scores: np.ndarray, min_score: float) -> list[int | None]:
    """Assign stretches to postures in order: ``scores`` (6, S) the best score of each
    posture in each stretch; returns per posture the stretch index or None (not found),
    stretches strictly increasing, maximising the total score of the found ones (a posture
    left out counts ``min_score``)."""
    n_pose, n_str = scores.shape
    # best[k][s]: best total for postures k.. using stretches s..
    best = np.zeros((n_pose + 1, n_str + 1))
    take = np.zeros((n_pose, n_str + 1), dtype=np.int8)
    for k in range(n_pose - 1, -1, -1):
        for s in range(n_str, -1, -1):
            options = [(best[k + 1][s] + min_score, 0)]  # posture k not found
            if s < n_str:
                options.append((best[k][s + 1], 1))  # stretch s unused
                if scores[k, s] >= min_score:
                    options.append((best[k + 1][s + 1] + scores[k, s], 2))
            best[k][s], take[k][s] = max(options)
    out: list[int | None] = []
    k = s = 0
    while k < n_pose:
        step = take[k][s]
        if step == 0:
            out.append(None)
            k += 1
        elif step == 1:
            s += 1
        else:
            out.append(s)
            k += 1
            s += 1
    return out


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = float((a | b).sum())
    return float((a & b).sum()) / union if union else 0.0


def held_frames(
    masks: np.ndarray, chosen: int, first: int, last: int, count: int, min_iou: float
) -> list[int]:
    """The frames to combine with frame ``chosen`` (ascending, ``chosen`` among them).

    Grows a contiguous run from ``chosen`` one frame at a time, alternately after and before
    it, within ``first``..``last``, up to ``count`` frames; a side stops at the first frame
    whose silhouette's intersection over union with the chosen frame's is below ``min_iou``
    (``masks`` (N, H, W) bool, indexed by frame)."""
    lo = hi = chosen
    open_after, open_before = True, True
    while hi - lo + 1 < count and (open_after or open_before):
        if open_after:
            if hi + 1 <= last and _iou(masks[hi + 1], masks[chosen]) >= min_iou:
                hi += 1
            else:
                open_after = False
        if hi - lo + 1 < count and open_before:
            if lo - 1 >= first and _iou(masks[lo - 1], masks[chosen]) >= min_iou:
                lo -= 1
            else:
                open_before = False
    return list(range(lo, hi + 1))


def median_frame(frames: torch.Tensor, indices: list[int]) -> np.ndarray:
    """(H, W, 3) uint8 RGB: the per-pixel, per-channel median of ``frames[indices]``
    (frames (N, 3, H, W) uint8 or float in [0, 1]; the mean of the two middle values for an
    even count, rounded)."""
    stack = frames[indices].permute(0, 2, 3, 1).double().numpy()
    if frames.dtype != torch.uint8:
        stack = stack * 255.0
    return np.clip(np.round(np.median(stack, axis=0)), 0, 255).astype(np.uint8)


def capture_from_frames(
    frames: torch.Tensor,
    camera: Camera,
    model: BodyModel,
    height_m: float | None = None,
    segmentation: SegmentationOptions | None = None,
    options: CaptureOptions | None = None,
    progress=None,
) -> CaptureResult:
    """Choose the background frames and one frame per posture.

    Args:
        frames: (N, 3, H, W) RGB, uint8 or float in [0, 1], the video.
        camera: the calibrated camera (B = 1) of the video.
        model: the template body model.
        height_m: the person's height (None: each template is scaled to the silhouette).
        segmentation: the segmentation chain's options.
        options: see :class:`CaptureOptions`.
        progress: optional factory ``total -> bar`` (``update(n)``, ``close()``).

    Raises:
        DataError: fewer than 5 empty frames at the start, or frames of the wrong size.
    """
    options = options or CaptureOptions()
    segmentation = segmentation or SegmentationOptions()
    w, h = camera.image_size
    if tuple(frames.shape[-2:]) != (h, w):
        raise DataError(
            f"video frames are {frames.shape[-1]}x{frames.shape[-2]} pixels, camera.yaml "
            f"image_size is {w}x{h}"
        )
    n_empty = empty_start(frames, options)
    if n_empty < MIN_BACKGROUND_FRAMES:
        raise DataError(
            f"the video starts with {n_empty} frames of the empty scene, at least "
            f"{MIN_BACKGROUND_FRAMES} are needed (start recording before stepping in)"
        )
    result = CaptureResult(background=list(range(min(n_empty, options.max_background))))
    model_bg = fit_background(_float(frames[result.background]), segmentation)
    masks = []
    bar = progress(frames.shape[0] - n_empty) if progress else None
    for start in range(n_empty, frames.shape[0], 8):
        batch = _float(frames[start : start + 8])
        masks.append(segment(batch, model_bg, segmentation).masks[:, 0])
        if bar:
            bar.update(batch.shape[0])
    if bar:
        bar.close()
    masks_t = torch.cat(masks) if masks else torch.zeros(0, h, w, dtype=torch.bool)
    result.stretches = still_stretches(masks_t, n_empty, options)
    templates = template_silhouettes(model, camera, height_m)
    table = np.zeros((N_POSES, len(result.stretches)))
    where = np.zeros((N_POSES, len(result.stretches)), dtype=np.int64)
    host = masks_t.numpy()
    for s, (a, b) in enumerate(result.stretches):
        for i in range(a, b + 1):
            for k in range(N_POSES):
                score = match_score(host[i - n_empty], templates[k], height_m is None)
                if score > table[k, s]:
                    table[k, s], where[k, s] = score, i
    picks = choose_frames(table, options.min_score)
    for k, s in enumerate(picks, start=1):
        result.scores[k] = float(table[k - 1].max()) if table.shape[1] else 0.0
        if s is None:
            result.missing.append(k)
        else:
            result.chosen[k] = int(where[k - 1, s])
            result.scores[k] = float(table[k - 1, s])
            a, b = result.stretches[s]
            local = held_frames(
                host,
                result.chosen[k] - n_empty,
                a - n_empty,
                b - n_empty,
                options.hold_frames,
                options.hold_iou,
            )
            result.combined[k] = [i + n_empty for i in local]
            chosen = masks_t[result.chosen[k] - n_empty]
            result.cut[k] = cut_borders(chosen[None, None])[0]
    return result
