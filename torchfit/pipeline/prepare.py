"""The image side of a run, per subject: read the frames, segment the postures (or read the
subject's own masks), and build the person data the fit needs.

Where the silhouettes come from is ``segmentation.method``, resolved per subject by
:func:`torchfit.io.load_subject` (``Subject.method``): ``background`` subtraction, the
subject's ``masks/``, or ``chroma_key``."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from torchfit.camera import Camera
from torchfit.config.schema import Config
from torchfit.errors import DataError, SegmentationError
from torchfit.fit.person import PersonData, person_data_from_masks
from torchfit.image.background import fit_background
from torchfit.image.chroma import ChromaKeyOptions, chroma_key, despill, key_colour
from torchfit.image.plausibility import implausible
from torchfit.image.segment import SegmentationOptions, clean_mask, segment
from torchfit.io.dataset import Subject
from torchfit.io.images import load_frames, read_mask

__all__ = ["PreparedSubject", "segment_subject", "read_masks", "prepare_subject", "person_data"]


@dataclass
class PreparedSubject:
    """A segmented subject, ready to fit.

    Attributes:
        subject: the dataset entry.
        images: (6, 3, H, W) RGB in [0, 1].
        masks: (6, H, W) bool silhouettes.
        shadow: (6, H, W) bool, pixels the shadow test removed.
        seconds: time spent reading and segmenting.
    """

    subject: Subject
    images: torch.Tensor
    masks: torch.Tensor
    shadow: torch.Tensor
    seconds: float


def segment_subject(
    subject: Subject, segmentation: SegmentationOptions | Config
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Segment a subject's six posture images: background subtraction, chroma key or the
    subject's own masks, as ``subject.method`` says (no shadow pixels but with background
    subtraction).

    Args:
        subject: the dataset entry.
        segmentation: the segmentation options (or a whole config, whose ``segmentation``
            section is used).

    Returns:
        images (6, 3, H, W) in [0, 1], silhouettes (6, H, W) bool and the pixels the shadow
        test removed (6, H, W) bool.

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
    shadow = None
    if subject.method == "masks":
        masks = read_masks(subject)
    elif subject.method == "chroma_key":
        images, masks = _chroma_key(subject, images, segmentation)
    else:
        background, _ = load_frames(subject.background, size=size)
        seg = segment(images, fit_background(background, segmentation), segmentation)
        masks, shadow = seg.masks[:, 0], seg.shadow[:, 0]
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
    if shadow is None:
        shadow = torch.zeros_like(masks)
    return images, masks, shadow


def read_masks(subject: Subject) -> torch.Tensor:
    """The subject's own silhouettes ``masks/pose1`` … ``pose6`` as (6, H, W) bool (> 127 is
    the person).

    Raises:
        DataError: a mask missing, unreadable, not 8-bit single-channel, or not the size of
        ``camera.yaml``'s ``image_size``.
    """
    if not subject.masks:
        raise DataError(f"{subject.folder / 'masks'}: no masks/ folder")
    width, height = subject.camera.image_size
    out = []
    for path in subject.masks:
        mask = read_mask(path)
        if mask.shape != (height, width):
            raise DataError(
                f"{path}: mask is {mask.shape[1]}x{mask.shape[0]} pixels, camera.yaml "
                f"image_size is {width}x{height}"
            )
        out.append(mask > 127)
    return torch.from_numpy(np.stack(out))


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
    raw = chroma_key(images, options, background, key)
    masks = clean_mask(
        raw,
        segmentation.open_kernel,
        segmentation.close_kernel,
        segmentation.fill_holes,
        segmentation.largest_region,
        segmentation.max_hole_area,
    )
    if options.despill:
        images = despill(images, masks, key, options.spill_px)
    return images, masks[:, 0]


def prepare_subject(subject: Subject, config: Config) -> PreparedSubject:
    """Read and segment one subject (raises as :func:`segment_subject`)."""
    t0 = time.perf_counter()
    images, masks, shadow = segment_subject(subject, config.segmentation)
    return PreparedSubject(subject, images, masks, shadow, time.perf_counter() - t0)


def person_data(
    config: Config,
    masks: torch.Tensor,
    shadow: torch.Tensor,
    cameras: Camera,
    dtype: torch.dtype,
) -> PersonData:
    """The person side of the fit from segmented postures (B, J, H, W), as ``config`` says
    (distance transform, contour stride, shadow pixels as uncertain)."""
    use_shadow = config.fit.ignore_shadow and config.segmentation.shadow_test
    return person_data_from_masks(
        masks,
        cameras,
        config.segmentation.distance,
        config.fit.contour_stride,
        dtype,
        shadow if use_shadow else None,
        config.fit.shadow_margin_px,
    )
