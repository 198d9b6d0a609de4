"""A subject's stereo pair → segmented views → labelled joints → 3-D joints → lengths.

Conventions as in :mod:`torchfit.parts.stereo`. One subject whose rules fail gets a status and
a reason (``"left view: neck: ..."``); it never raises for content, so a batch run finishes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch

from torchfit.image.background import BackgroundModel, fit_background
from torchfit.image.morphology import fill_holes
from torchfit.image.plausibility import implausible
from torchfit.image.segment import SegmentationOptions, segment
from torchfit.io.dataset import StereoInfo
from torchfit.io.images import load_frames, read_image
from torchfit.parts.correspond import corresponding_joints
from torchfit.parts.decompose import decompose_cactus
from torchfit.parts.depth import joints_at_depth, outline_depths
from torchfit.parts.options import PartsOptions
from torchfit.parts.rules import Labelling
from torchfit.parts.stereo import stereo_measurements, triangulate_midpoint

__all__ = ["ViewResult", "StereoResult", "segment_view", "measure_stereo_pair"]


@dataclass
class ViewResult:
    """One view of the stereo pair.

    Attributes:
        image: ``(H, W, 3)`` uint8 RGB.
        mask: ``(H, W)`` bool silhouette.
        labelling: the joints found on it.
    """

    image: np.ndarray
    mask: np.ndarray
    labelling: Labelling


@dataclass
class StereoResult:
    """The stereo measurement of one subject.

    Attributes:
        status: ``"ok"`` or ``"failed"``.
        failed_rule: the rule that failed (``"segmentation"``, ``"contour"``, a rule of
            :data:`torchfit.parts.rules.RULE_NAMES`, or ``"stereo"`` when no matched outline
            lies near a joint), None when ok.
        message: the reason, naming the view ("" when ok).
        joints_world: joint name -> ``[x, y, z]`` metres (empty when failed).
        ray_gap_m: joint name -> distance between the two viewing rays, metres.
        measurements: key -> metres (empty when failed).
        views: ``"left"``, ``"right"`` -> :class:`ViewResult` (those that were processed).
        notes: what is worth knowing about an ok result (a view segmented a second time).
        pixels: ``"left"``, ``"right"`` -> joint name -> ``(2,)`` the pixels triangulated
            (after stereo matching, when on).
    """

    status: str = "failed"
    failed_rule: str | None = None
    message: str = ""
    joints_world: dict[str, list[float]] = field(default_factory=dict)
    ray_gap_m: dict[str, float] = field(default_factory=dict)
    measurements: dict[str, float] = field(default_factory=dict)
    views: dict[str, ViewResult] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    pixels: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


def _load_view(
    image_path, background_paths, config: SegmentationOptions
) -> tuple[np.ndarray, BackgroundModel]:
    """One view's image, ``(H, W, 3)`` uint8 RGB, and the background model of its frames."""
    image = read_image(image_path)
    frames, _ = load_frames(background_paths, size=(image.shape[1], image.shape[0]))
    return image, fit_background(frames, config)


def _mask(image: np.ndarray, model: BackgroundModel, config: SegmentationOptions):
    """``(H, W)`` bool silhouette with its holes left unfilled, or None when no person was
    found. Holes stay open: a hole between the legs marks the crotch (decompose_cactus fills
    the rest itself)."""
    config = dataclasses.replace(config, fill_holes=False)
    img = torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255.0
    result = segment(img, model, config)
    if not bool(result.found[0]):
        return None
    return result.masks[0, 0].cpu().numpy()


def segment_view(
    image_path, background_paths, config: SegmentationOptions
) -> tuple[np.ndarray, np.ndarray | None]:
    """Segment one view against its background frames.

    Returns:
        ``(image, mask)``: ``(H, W, 3)`` uint8 RGB and ``(H, W)`` bool with its holes left
        unfilled, or None when no person was found.
    """
    image, model = _load_view(image_path, background_paths, config)
    return image, _mask(image, model, config)


def _label_view(
    image: np.ndarray,
    model: BackgroundModel,
    segmentation: SegmentationOptions,
    parts: PartsOptions,
) -> tuple[ViewResult | None, tuple[str, str] | None]:
    """Segment and label one view: ``(view, None)``, or ``(view or None, (rule, message))``."""
    mask = _mask(image, model, segmentation)
    if mask is None:
        return None, ("segmentation", "no person found")
    why = implausible(torch.from_numpy(mask)[None, None], segmentation.plausibility)[0]
    if why:
        return None, ("segmentation", f"segmentation implausible: {why}")
    labelling = decompose_cactus(mask, image, parts)
    view = ViewResult(image, mask, labelling)
    if not labelling.ok:
        return view, (labelling.failed_rule, f"{labelling.failed_rule}: {labelling.message}")
    return view, None


def measure_stereo_pair(
    stereo: StereoInfo,
    parts: PartsOptions | None = None,
    segmentation: SegmentationOptions | None = None,
) -> StereoResult:
    """Segment, label and triangulate one subject's posture-5 stereo pair.

    Args:
        stereo: the subject's :class:`~torchfit.io.dataset.StereoInfo`.
        parts: decomposition options.
        segmentation: background subtraction options (for the synthetic rooms with floor
            shadows use ``gamma: 0.05``).

    A view whose silhouette fails the rules is segmented once more with
    ``segmentation.shadow_bridge`` (when the shadow test is on and the bridge is not).

    Returns:
        A :class:`StereoResult`; failures carry the rule and the view (a silhouette that
        cannot be a person, :func:`~torchfit.image.plausibility.implausible`, fails the rule
        ``"segmentation"``).

    Raises:
        DataError: an image or background frame cannot be read.
    """
    parts = parts or PartsOptions()
    segmentation = segmentation or SegmentationOptions()
    out = StereoResult()
    # a view whose silhouette breaks the body's rules is segmented once more with
    # segmentation.shadow_bridge (shadow-like pixels with person above and below them in their
    # column stay person: a white leg before a white wall is not cut off); the first failure
    # is the one reported when both fail
    attempts = [segmentation]
    if segmentation.shadow_test and not segmentation.shadow_bridge:
        attempts.append(dataclasses.replace(segmentation, shadow_bridge=True))
    for side in ("left", "right"):
        # the image and background model serve every attempt (the bridge does not change
        # the background model)
        image, model = _load_view(
            getattr(stereo, f"{side}_image"), getattr(stereo, f"background_{side}"), segmentation
        )
        failure = None
        for k, options in enumerate(attempts):
            view, why = _label_view(image, model, options, parts)
            if why is None:
                out.views[side] = view
                if k > 0:
                    out.notes.append(f"{side} view: segmented with shadow_bridge")
                break
            if failure is None:
                failure = (view, why)
        else:
            view, (out.failed_rule, message) = failure
            if view is not None:
                out.views[side] = view
            out.message = f"{side} view: {message}"
            return out
    left, right = out.views["left"].labelling, out.views["right"].labelling
    if parts.stereo_match and parts.stereo_depth == "outline":
        _, _, trunk = left.body_frame()
        jl, jr = left.joints, right.joints
        guess = np.median([jr[n] - jl[n] for n in jl if n in jr], axis=0)
        outline = outline_depths(
            fill_holes(out.views["left"].mask),
            fill_holes(out.views["right"].mask),
            guess,
            stereo.left,
            stereo.right,
            search_px=parts.match_search_px,
        )
        out.joints_world, out.ray_gap_m = joints_at_depth(
            outline, jl, jr, stereo.left, stereo.right, parts.depth_sigma * trunk
        )
        out.pixels = {"left": jl, "right": jr}
        missing = [n for n in jl if n in jr and n not in out.joints_world]
        if missing:
            out.failed_rule = "stereo"
            out.message = f"no matched outline near {missing}"
            return out
        joints = {n: torch.tensor([v], dtype=torch.float64) for n, v in out.joints_world.items()}
    else:
        joints = _triangulate_labels(out, stereo, parts)
    out.measurements = {k: float(v[0]) for k, v in stereo_measurements(joints).items()}
    out.status = "ok"
    return out


def _triangulate_labels(
    out: StereoResult, stereo: StereoInfo, parts: PartsOptions
) -> dict[str, torch.Tensor]:
    """Triangulate the labelled joints (after matching their anchors, with ``stereo_match``)
    by the midpoint method; fills ``out.pixels``, ``joints_world`` and ``ray_gap_m``."""
    left, right = out.views["left"].labelling, out.views["right"].labelling
    jl, jr = left.joints, right.joints
    if parts.stereo_match:
        _, _, trunk = left.body_frame()
        jl, jr = corresponding_joints(
            fill_holes(out.views["left"].mask),
            fill_holes(out.views["right"].mask),
            left.joints,
            right.joints,
            left.anchors,
            right.anchors,
            stereo.left,
            stereo.right,
            parts.match_radius * trunk,
            parts.match_search_px,
        )
    out.pixels = {"left": jl, "right": jr}
    names = [n for n in jl if n in jr]
    pl = torch.tensor(np.stack([jl[n] for n in names]), dtype=torch.float64)[None]
    pr = torch.tensor(np.stack([jr[n] for n in names]), dtype=torch.float64)[None]
    points, gap = triangulate_midpoint(pl, stereo.left, pr, stereo.right)
    out.joints_world = {n: [float(x) for x in points[0, i]] for i, n in enumerate(names)}
    out.ray_gap_m = {n: float(gap[0, i]) for i, n in enumerate(names)}
    return {n: points[:, i] for i, n in enumerate(names)}
