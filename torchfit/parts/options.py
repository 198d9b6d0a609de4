"""Options of the silhouette part decomposition (second paper)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

__all__ = ["PartsOptions"]


@dataclass(frozen=True)
class PartsOptions:
    """Silhouette part decomposition: spline, curvature extrema, rules, wrists, stereo matching.

    Lengths given as fractions are relative to the silhouette height ``H`` (curve options) or
    to the 2-D trunk length ``T`` (neck cut middle to crotch; joint offsets), so that they do
    not depend on the image scale. See :mod:`torchfit.parts` for the rules.

    Attributes:
        smoothing_px: RMS distance spline - contour pixels (0: interpolation).
        point_spacing: use every n-th contour pixel.
        min_curvature: significance: ``|curvature| * H`` above this.
        min_separation: extrema closer than this * H along the outline merge.
        hand_exclusion: inner-elbow candidates > this * T above the neck are hands.
        wrists: find the wrists from skin colour.
        skin_threshold: Mahalanobis distance to the face's skin chromaticity.
        hand_start: hand pixels lie beyond this fraction of elbow -> hand tip.
        face_band: skin is learnt this fraction of the way from the neck to the top.
        offset_back, offset_neck, offset_shoulder, offset_elbow, offset_wrist: systematic
            cut-point -> joint-centre corrections (:class:`torchfit.parts.JointOffsets`),
            (down, out) in units of the 2-D trunk length; the median of label -> projected
            joint centre on the synthetic development subjects (seed 1000), never the test
            set: ``python benchmarks/calibrate_parts.py --data <dev set>`` with
            configs/stereo.yaml.
        stereo_match: refine each joint's right-view pixel by matching the two silhouettes
            along the epipolar line around its outline anchors (false: the paper's
            independent labelling of both views).
        match_radius: matching window half-size, * T.
        match_search_px: search +- this along the epipolar line, pixels.
        stereo_depth: with ``stereo_match``, where a joint's depth comes from: ``outline``
            matches the whole left outline, weighting each point by how well its edge fixes
            a shift along the epipolar line, and takes the weighted median depth of the
            outline around the joint (:mod:`torchfit.parts.depth`); ``anchors`` matches the
            joint's own cut ends only (blind where a limb lies along the epipolar line).
        depth_sigma: ``outline``: the neighbourhood of a joint on the outline, * T.
    """

    smoothing_px: float = 1.0
    point_spacing: int = 1
    min_curvature: float = 8.0
    min_separation: float = 0.02
    hand_exclusion: float = 0.25
    wrists: bool = True
    skin_threshold: float = 3.0
    hand_start: float = 0.4
    face_band: float = 0.45
    offset_back: tuple[float, float] = (-0.184, 0.0)
    offset_neck: tuple[float, float] = (0.060, 0.0)
    offset_shoulder: tuple[float, float] = (0.049, 0.058)
    offset_elbow: tuple[float, float] = (0.014, 0.028)
    offset_wrist: tuple[float, float] = (-0.009, 0.017)
    stereo_match: bool = True
    match_radius: float = 0.1
    match_search_px: float = 8.0
    stereo_depth: Literal["outline", "anchors"] = "outline"
    depth_sigma: float = 0.8
