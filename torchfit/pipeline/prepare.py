"""The image side of a run, per subject: read the frames, segment the postures (or read the
subject's own masks), and build the person data the fit needs.

Where the silhouettes come from is ``segmentation.method``, resolved per subject by
:func:`torchfit.io.load_subject` (``Subject.method``): ``background`` subtraction, the
subject's ``masks/``, or ``chroma_key``."""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from torchfit.camera import Camera, floor_points
from torchfit.config.schema import Config
from torchfit.errors import DataError, SegmentationError
from torchfit.fit.bends import parse_bends
from torchfit.fit.person import PersonData, person_data_from_masks
from torchfit.image.background import BackgroundModel, fit_background
from torchfit.image.chroma import ChromaKeyOptions, chroma_key, despill, key_colour
from torchfit.image.plausibility import cut_borders, implausible
from torchfit.image.segment import SegmentationOptions, clean_mask, segment
from torchfit.io.dataset import Subject
from torchfit.io.images import load_frames, read_silhouette

__all__ = [
    "PreparedSubject",
    "segment_subject",
    "segment_postures",
    "floor_reach",
    "reach_floor",
    "floor_retry_options",
    "read_masks",
    "chroma_silhouettes",
    "prepare_subject",
    "compact_images",
    "person_data",
]

log = logging.getLogger(__name__)


@dataclass
class PreparedSubject:
    """A segmented subject, ready to fit.

    Attributes:
        subject: the dataset entry.
        images: (6, 3, H, W) RGB: ``uint8`` where they are the files' own 8-bit values (a
            quarter of the memory of float32: 7.5 MB a subject at 720x576, which counts in
            large batches), else float in [0, 1] (e.g. after the chroma key's despill);
            :meth:`float_images` gives float in [0, 1] either way.
        masks: (6, H, W) bool silhouettes.
        shadow: (6, H, W) bool, pixels the shadow test removed.
        seconds: time spent reading and segmenting.
        notes: what the segmentation did beyond the configured chain (a posture segmented
            again, see :func:`reach_floor`).
        flags: what makes the silhouettes doubtful (one that does not reach the floor); the
            judge makes the subject ``poor_fit`` with them. ``params.json`` lists both.
    """

    subject: Subject
    images: torch.Tensor
    masks: torch.Tensor
    shadow: torch.Tensor
    seconds: float
    notes: list[str] = field(default_factory=list)
    flags: list[str] = field(default_factory=list)

    def float_images(self, index: list[int] | None = None) -> torch.Tensor:
        """The images (or those of the postures ``index``, 0-based) in [0, 1], as read."""
        images = self.images if index is None else self.images[index]
        if images.dtype == torch.uint8:
            return images.float().div_(255.0)  # what the reader computes from the same bytes
        return images


def compact_images(images: torch.Tensor) -> torch.Tensor:
    """Float images in [0, 1] as ``uint8`` where that holds them exactly (read from 8-bit
    files and not changed since), else as they are."""
    if images.dtype != torch.float32:
        return images
    packed = images.mul(255.0).round_().clamp_(0, 255).to(torch.uint8)
    return packed if torch.equal(packed.float().div_(255.0), images) else images


def segment_subject(
    subject: Subject, segmentation: SegmentationOptions | Config
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`segment_postures` without its notes: images, silhouettes and shadow pixels."""
    images, masks, shadow, _, _ = segment_postures(subject, segmentation)
    return images, masks, shadow


def segment_postures(
    subject: Subject, segmentation: SegmentationOptions | Config
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[str], list[str]]:
    """Segment a subject's six posture images: background subtraction, chroma key or the
    subject's own masks, as ``subject.method`` says (no shadow pixels but with background
    subtraction), and check that every silhouette reaches the floor (:func:`reach_floor`).

    Args:
        subject: the dataset entry.
        segmentation: the segmentation options (or a whole config, whose ``segmentation``
            section is used).

    Returns:
        images (6, 3, H, W) in [0, 1], silhouettes (6, H, W) bool, the pixels the shadow
        test removed (6, H, W) bool, notes on what was done beyond the configured chain (a
        posture segmented again), and flags (silhouettes that do not reach the floor or that
        the image frame cuts, :func:`frame_cuts`).

    Raises:
        DataError: invalid subject folder, or a mask that cannot be read or has the wrong
        size; SegmentationError: no person in a posture image,
        or a silhouette no person in that posture can have
        (:func:`~torchfit.image.plausibility.implausible`): ``"segmentation implausible in
        pose4: it covers 100 % of the image (at most 50 %); ..."``.
    """
    if isinstance(segmentation, Config):
        segmentation = segmentation.segmentation
    if subject.problems:
        raise DataError("; ".join(subject.problems))
    size = subject.camera.image_size
    images, _ = load_frames(subject.poses, size=size)
    shadow, model = None, None
    if subject.method == "masks":
        masks = read_masks(subject)
    elif subject.method == "chroma_key":
        images, masks = _chroma_key(subject, images, segmentation)
    else:
        background, _ = load_frames(subject.background, size=size)
        model = fit_background(background, segmentation)
        seg = segment(images, model, segmentation)
        masks, shadow = seg.masks[:, 0], seg.shadow[:, 0]
    if shadow is None:
        shadow = torch.zeros_like(masks)
    # before the checks below: a silhouette segmented again may pass them where the first fails
    masks, shadow, notes, flags = reach_floor(
        images, model, masks, shadow, subject.camera, segmentation
    )
    missing = [
        f"pose{i + 1} ({subject.poses[i].name})"
        for i, ok in enumerate(masks.flatten(1).any(1).tolist())
        if not ok
    ]
    if missing:
        raise SegmentationError(f"no person found in {', '.join(missing)}")
    reasons = implausible(masks[:, None], segmentation.plausibility)
    wrong = [f"pose{i + 1}: {why}" for i, why in enumerate(reasons) if why]
    if wrong:
        raise SegmentationError(f"segmentation implausible in {'; in '.join(wrong)}")
    return images, masks, shadow, notes, flags + frame_cuts(masks)


def frame_cuts(masks: torch.Tensor) -> list[str]:
    """One flag per silhouette the image frame cuts (a hand or the feet outside the picture).

    The fit leaves the frame's run of the outline out (:func:`person_data_from_masks`), so the
    model reaches beyond it, but what lies beyond is not measured: the lengths through that
    part rest on the other postures (a T-pose whose hands are cut says nothing of the arm
    span). Such a posture is a flag: the judge makes the subject ``poor_fit``.

    Args:
        masks: (J, H, W) bool silhouettes.

    Returns:
        e.g. ``"pose4: the image frame cuts the silhouette (left, right border): its parts
        beyond the picture are not measured, check the overlays"``.
    """
    return [
        f"pose{j + 1}: the image frame cuts the silhouette ({', '.join(cut)} border): its parts "
        "beyond the picture are not measured, check the overlays"
        for j, cut in enumerate(cut_borders(masks[:, None]))
        if cut
    ]


def floor_reach(masks: torch.Tensor, camera: Camera) -> list[float]:
    """How far from the floor mark each silhouette's lowest pixel sees the floor.

    Args:
        masks: (J, H, W) bool silhouettes.
        camera: their camera (batch 1).

    Returns:
        per silhouette, metres between the world origin and the floor point seen at the mean
        column of its lowest row; ``inf`` for an empty silhouette or a row at or above the
        horizon.
    """
    rows, pixels = [], []
    for j, mask in enumerate(masks):
        ys = torch.nonzero(mask.any(dim=1)).flatten()
        if ys.numel():
            v = int(ys[-1])
            rows.append(j)
            pixels.append([float(torch.nonzero(mask[v]).float().mean()), float(v)])
    reach = [float("inf")] * masks.shape[0]
    if pixels:
        points = floor_points(torch.tensor([pixels], dtype=torch.float64), camera)[0]
        for j, d in zip(rows, points[:, :2].norm(dim=1).tolist(), strict=True):
            reach[j] = d if math.isfinite(d) else float("inf")
    return reach


def floor_retry_options(segmentation: SegmentationOptions, band: float) -> SegmentationOptions:
    """The options of :func:`reach_floor`'s second attempt: the shadow test confined to the
    lowest ``band`` of the foreground (or its own band where lower), with the bridge."""
    band = min(segmentation.shadow_band, band)
    return replace(segmentation, shadow_bridge=True, shadow_band=band)


def reach_floor(
    images: torch.Tensor,
    model: BackgroundModel | None,
    masks: torch.Tensor,
    shadow: torch.Tensor,
    camera: Camera,
    segmentation: SegmentationOptions,
) -> tuple[torch.Tensor, torch.Tensor, list[str], list[str]]:
    """Find the postures whose silhouette lost its feet and, on request, segment them again.

    Every posture stands on the floor mark (within a step of it), so a silhouette whose lowest
    pixel sees the floor further than ``segmentation.floor_reach_m`` from the mark has lost
    its lower legs: most often the shadow test took a leg for a cast shadow (a light leg
    before a light floor or wall is an attenuated copy of it) and the clean-up then dropped
    what was cut off. Such a posture is a flag (the judge makes the subject ``poor_fit``).

    With ``segmentation.floor_retry`` (and background subtraction with the shadow test), those
    postures are first segmented once more: the shadow test confined to the lowest
    ``segmentation.floor_retry_band`` of the foreground (where the feet's own cast shadow
    lies), with ``shadow_bridge`` (shadow-like pixels with the person above and below them in
    their column stay person). The new silhouette is kept where it reaches the floor.

    Args:
        images: (J, 3, H, W) the posture images.
        model: their background model (None: the silhouettes did not come from background
            subtraction, nothing is segmented again).
        masks, shadow: (J, H, W) silhouettes and shadow pixels.
        camera: the subject's camera.
        segmentation: ``floor_reach_m`` (None: nothing is checked), ``floor_retry``,
            ``floor_retry_band`` and the options of the first segmentation.

    Returns:
        silhouettes, shadow pixels, one note per posture segmented again, and one flag per
        posture whose silhouette still does not reach the floor.
    """
    limit = getattr(segmentation, "floor_reach_m", None)
    if limit is None:
        return masks, shadow, [], []
    reach = floor_reach(masks, camera)
    short = [j for j, d in enumerate(reach) if not d <= limit]
    notes: list[str] = []
    retry = (
        getattr(segmentation, "floor_retry", False)
        and model is not None
        and segmentation.shadow_test
        and not segmentation.shadow_bridge
    )
    if short and retry:
        band = getattr(segmentation, "floor_retry_band", 1.0)
        again = segment(images[short], model, floor_retry_options(segmentation, band))
        again_reach = floor_reach(again.masks[:, 0], camera)
        masks, shadow = masks.clone(), shadow.clone()
        for k, j in enumerate(short):
            if again_reach[k] <= limit:
                masks[j], shadow[j] = again.masks[k, 0], again.shadow[k, 0]
                notes.append(
                    f"pose{j + 1}: the silhouette saw the floor {reach[j]:.2f} m from the mark; "
                    f"segmented again ({again_reach[k]:.2f} m)"
                )
                log.info(notes[-1])
                reach[j] = again_reach[k]
    # where the retry was possible but not asked for, the flag says how to ask
    hint = (
        " (segmentation.floor_retry: true segments such a posture once more)"
        if model is not None
        and segmentation.shadow_test
        and not retry
        and not segmentation.shadow_bridge
        else ""
    )
    flags = [
        f"pose{j + 1}: the silhouette does not reach the floor (its lowest pixel sees it "
        f"{reach[j]:.2f} m from the mark): the segmentation lost the lower legs, check the "
        f"overlays{hint}"
        for j in range(len(reach))
        if not reach[j] <= limit
    ]
    return masks, shadow, notes, flags


def read_masks(subject: Subject) -> torch.Tensor:
    """The subject's own silhouettes ``masks/pose1`` … ``pose6`` as (6, H, W) bool (> 127 is
    the person).

    Raises:
        DataError: a mask missing, unreadable, not 8-bit single-channel, or not the size of
        ``camera.yaml``'s ``image_size``; or one with no pixel above 127 but some above 0
        (a mask stored as 0 and 1, say, where 255 is the person).
    """
    if not subject.masks:
        raise DataError(f"{subject.folder / 'masks'}: no masks/ folder")
    size = subject.camera.image_size
    return torch.from_numpy(np.stack([read_silhouette(p, size) for p in subject.masks]))


def _chroma_key(
    subject: Subject, images: torch.Tensor, segmentation: SegmentationOptions
) -> tuple[torch.Tensor, torch.Tensor]:
    options = getattr(segmentation, "chroma_key", ChromaKeyOptions())
    background = None
    if subject.background:
        background, _ = load_frames(subject.background, size=subject.camera.image_size)
    elif options.key is None:
        raise DataError(
            f"{subject.folder / 'background'}: chroma key needs background frames to estimate "
            "the key colour, or segmentation.chroma_key.key"
        )
    key = key_colour(options, background, images.dtype, images.device)
    masks = chroma_silhouettes(images, segmentation, background, key)
    if options.despill:
        images = despill(images, masks, key, options.spill_px)
    return images, masks[:, 0]


def chroma_silhouettes(
    images: torch.Tensor,
    segmentation: SegmentationOptions,
    screen: torch.Tensor | None,
    key: torch.Tensor,
) -> torch.Tensor:
    """(B, 1, H, W) bool silhouettes of chroma-keyed images (B, 3, H, W): the key
    (:func:`~torchfit.image.chroma.chroma_key`, ``segmentation.chroma_key``'s options, the
    empty screen's frames ``screen`` or None) cleaned as background subtraction's are."""
    options = getattr(segmentation, "chroma_key", ChromaKeyOptions())
    return clean_mask(
        chroma_key(images, options, screen, key),
        segmentation.open_kernel,
        segmentation.close_kernel,
        segmentation.fill_holes,
        segmentation.largest_region,
        segmentation.max_hole_area,
        segmentation.join_parts,
    )


def prepare_subject(subject: Subject, config: Config) -> PreparedSubject:
    """Read and segment one subject (raises as :func:`segment_subject`)."""
    t0 = time.perf_counter()
    images, masks, shadow, notes, flags = segment_postures(subject, config.segmentation)
    seconds = time.perf_counter() - t0
    return PreparedSubject(subject, compact_images(images), masks, shadow, seconds, notes, flags)


def person_data(
    config: Config,
    masks: torch.Tensor,
    shadow: torch.Tensor,
    cameras: Camera,
    dtype: torch.dtype,
) -> PersonData:
    """The person side of the fit from segmented postures (B, J, H, W), as ``config`` says
    (distance transform, contour stride, shadow pixels as uncertain; the silhouettes of the
    postures with bent-joint marks where ``fit.bends`` weighs them)."""
    use_shadow = config.fit.ignore_shadow and config.segmentation.shadow_test
    person = person_data_from_masks(
        masks,
        cameras,
        config.segmentation.distance,
        config.fit.contour_stride,
        dtype,
        shadow if use_shadow else None,
        config.fit.shadow_margin_px,
        normals=config.fit.contour_orientation_px > 0,
    )
    if config.fit.bends.weight > 0:
        marked = {b.posture for b in parse_bends(config.fit.bends.joints)}
        person.silhouettes = {k: masks[:, k] for k, j in enumerate(config.fit.poses) if j in marked}
    return person
