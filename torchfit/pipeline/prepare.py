"""The image side of a run, per subject: read the frames, segment the postures, and build the
person data the fit needs."""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from torchfit.camera import Camera
from torchfit.config.schema import Config
from torchfit.errors import DataError, SegmentationError
from torchfit.fit.person import PersonData, person_data_from_masks
from torchfit.image.background import fit_background
from torchfit.image.plausibility import implausible
from torchfit.image.segment import SegmentationOptions, segment
from torchfit.io.dataset import Subject
from torchfit.io.images import load_frames

__all__ = ["PreparedSubject", "segment_subject", "prepare_subject", "person_data"]


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
    """Segment a subject's six posture images.

    Args:
        subject: the dataset entry.
        segmentation: the segmentation options (or a whole config, whose ``segmentation``
            section is used).

    Returns:
        images (6, 3, H, W) in [0, 1], silhouettes (6, H, W) bool and the pixels the shadow
        test removed (6, H, W) bool.

    Raises:
        DataError: invalid subject folder; SegmentationError: no person in a posture image,
        or a silhouette no person in that posture can have
        (:func:`~torchfit.image.plausibility.implausible`): ``"segmentation implausible in
        pose4: it covers 100 % of the image (at most 50 %); ..."``.
    """
    if isinstance(segmentation, Config):
        segmentation = segmentation.segmentation
    if subject.problems:
        raise DataError("; ".join(subject.problems))
    size = subject.camera.image_size
    background, _ = load_frames(subject.background, size=size)
    images, _ = load_frames(subject.poses, size=size)
    seg = segment(images, fit_background(background, segmentation), segmentation)
    missing = [
        f"pose{i + 1} ({subject.poses[i].name})"
        for i, ok in enumerate(seg.found.tolist())
        if not ok
    ]
    if missing:
        raise SegmentationError(f"no person found in {', '.join(missing)}")
    reasons = implausible(seg.masks, segmentation.plausibility)
    wrong = [f"pose{i + 1}: {why}" for i, why in enumerate(reasons) if why]
    if wrong:
        raise SegmentationError(f"segmentation implausible in {'; in '.join(wrong)}")
    return images, seg.masks[:, 0], seg.shadow[:, 0]


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
