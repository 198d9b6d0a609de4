"""The second paper's rules: label back, neck, shoulders and elbows on a posture-5 silhouette.

Posture 5 ("cactus", design.md section 4): facing the camera, shoulders abducted 90°, elbows
flexed 90° with the forearms pointing up, hips abducted 10°. Its outline has five convex
extremities (head, two hands, two feet) and, between them, the concavities the paper cuts at.

Conventions: points are ``(u, v)`` pixels, ``v`` **down** (design.md section 2). The person
faces the camera, so the person's **left** side (``l_shoulder``, ``l_elbow``) is on the image
**right** (larger ``u``).

The paper (section 2.3) states its rules with ``y`` up ("the back is the negative minimum with
the lowest y", "the neck is the cut between the two negative minima with the highest y", the
elbow cut joins the negative minimum and the positive maximum with the highest/lowest x). Taken
literally on a real cactus outline they pick the wrong points (a knee concavity is lower than
the crotch, a hand held slightly outwards is more lateral than the elbow). This module
implements their intent, made explicit with the outline's structure and the short-cut rule
(Singh et al.: of competing cuts, the shortest):

1. **Extremities.** Hands: the highest outline points on each side, at least
   ``0.2 W`` from the body's centre column (``W`` the silhouette width); feet: the lowest point on
   each side; head: the highest point within ``0.1 W`` of the centre column. Going round the
   outline they must come in the order head, hand, foot, foot, hand, with hand and foot of one
   side next to each other; this splits the outline into the *top arcs* (head → hand), the
   *outer arcs* (hand → foot) and the *inner arc* (foot → foot).
2. **Back.** The crotch: the apex (highest point) of the inner arc, which must hold a negative
   minimum (the paper's "lowest" minimum, y up; a rounded crotch between wide legs has its
   curvature minimum spread along the arch, the apex is stable). Where a floor shadow joins the
   feet the gap between the legs is a hole of the silhouette and its top is the crotch.
3. **Neck.** The shortest cut joining a negative minimum of the left top arc to one of the
   right top arc (the paper's "two highest minima"; ear or shoulder-slope concavities give
   longer cuts); the neck point is its middle.
4. **Principal axis.** Neck → back; it defines "lateral" for the rules below.
5. **Elbows.** The shortest cut joining a negative minimum of the top arc (the inner elbow,
   excluding the neck minimum and anything higher than ``hand_exclusion`` trunk lengths above
   the neck, i.e. the hand) to a positive maximum of the outer arc below it (the outer elbow).
6. **Shoulders.** The cut from the side's neck minimum (the side's "highest" minimum) to the
   armpit: the negative minimum of the outer arc between the outer elbow and the foot, above
   the crotch, that gives the shortest cut.

Where a rule finds nothing the labelling fails with that rule's name (``extremities``,
``back``, ``neck``, ``elbow``, ``shoulder``); nothing is reported for a silhouette whose
labelling failed.

Joint points are the cut middles and the crotch (the paper); :class:`JointOffsets` (applied by
:func:`torchfit.parts.decompose_cactus`) then moves them by systematic offsets that relate
these outline points to the joint centres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchfit.parts.curve import ContourSpline, CurvatureExtremum
from torchfit.parts.labels import (
    RULE_NAMES,
    Cut,
    JointOffsets,
    Labelling,
    RuleFailure,
)

__all__ = [
    "Cut",
    "JointOffsets",
    "RuleFailure",
    "Labelling",
    "label_cactus",
    "RULE_NAMES",
]


def _arc_contains(t0: float, t1: float, t: np.ndarray | float) -> np.ndarray:
    """Whether ``t`` lies on the arc running forwards from ``t0`` to ``t1`` (mod 1)."""
    return np.mod(np.asarray(t) - t0, 1.0) <= np.mod(t1 - t0, 1.0)


@dataclass
class _Arc:
    """The outline between two parameters ``a`` and ``b``, walked from ``a`` to ``b``
    (forwards in ``t`` when ``forward``, else backwards)."""

    a: float
    b: float
    forward: bool

    def contains(self, t: np.ndarray | float) -> np.ndarray:
        return (
            _arc_contains(self.a, self.b, t) if self.forward else _arc_contains(self.b, self.a, t)
        )

    def position(self, t: float) -> float:
        """Fraction of the way from ``a`` to ``b``."""
        sign = 1.0 if self.forward else -1.0
        span = np.mod(sign * (self.b - self.a), 1.0)
        return float(np.mod(sign * (t - self.a), 1.0) / max(span, 1e-12))


def _arc_between(a: float, b: float, others: list[float]) -> _Arc:
    """The arc from ``a`` to ``b`` that holds none of ``others``."""
    forward = not any(_arc_contains(a, b, o) for o in others)
    return _Arc(a, b, forward)


# --------------------------------------------------------------------------------------------
# The rules


def _extremities(t: np.ndarray, pts: np.ndarray, centre_u: float) -> dict[str, float]:
    width = float(np.ptp(pts[:, 0]))
    height = float(np.ptp(pts[:, 1]))
    if width <= 0 or height <= 0:
        raise RuleFailure("extremities", "the outline is degenerate (zero width or height)")
    lateral = pts[:, 0] - centre_u
    out: dict[str, float] = {}
    # The person's left is the image right (facing the camera).
    for side, sign in (("l", 1.0), ("r", -1.0)):
        arm = sign * lateral > 0.2 * width
        if not arm.any():
            raise RuleFailure("extremities", f"no {side} hand: nothing 0.2 W beside the body")
        i = int(np.flatnonzero(arm)[np.argmin(pts[arm, 1])])
        k = max(len(t) // 100, 2)
        neighbours = pts[[(i - k) % len(t), (i + k) % len(t)], 1]
        if not (neighbours >= pts[i, 1]).all():
            raise RuleFailure(
                "extremities",
                f"no {side} hand: the outline has no peak beside the body (no raised forearm)",
            )
        out[f"{side}_hand"] = float(t[i])
        leg = (sign * lateral > 0) & (pts[:, 1] > pts[:, 1].min() + 0.5 * height)
        if not leg.any():
            raise RuleFailure("extremities", f"no {side} foot in the lower half")
        out[f"{side}_foot"] = float(t[leg][np.argmax(pts[leg, 1])])
    head = np.abs(lateral) < 0.1 * width
    if not head.any():
        raise RuleFailure("extremities", "no head: nothing within 0.1 W of the centre column")
    out["head_top"] = float(t[head][np.argmin(pts[head, 1])])
    hand_v = min(pts[np.searchsorted(t, out[f"{s}_hand"]), 1] for s in "lr")
    head_v = pts[np.searchsorted(t, out["head_top"]), 1]
    foot_v = min(pts[np.searchsorted(t, out[f"{s}_foot"]), 1] for s in "lr")
    if not head_v < foot_v - 0.5 * height or hand_v > foot_v - 0.5 * height:
        raise RuleFailure("extremities", "head or hands are not in the upper half of the outline")
    # Cyclic order: head, hand, foot, foot, hand with one side's hand and foot adjacent.
    order = sorted(out, key=lambda k: np.mod(out[k] - out["head_top"], 1.0))
    if order not in (
        ["head_top", "l_hand", "l_foot", "r_foot", "r_hand"],
        ["head_top", "r_hand", "r_foot", "l_foot", "l_hand"],
    ):
        raise RuleFailure(
            "extremities", f"extremities out of order round the outline: {', '.join(order)}"
        )
    return out


def _check_ratio(rule: str, what: str, length: float, trunk: float, lo: float, hi: float) -> None:
    """Plausibility of a cut against the trunk length (turns a wrong labelling into a failure)."""
    if not lo * trunk <= length <= hi * trunk:
        raise RuleFailure(
            rule,
            f"{what} is {length / trunk:.2f} trunk lengths, outside the plausible {lo}–{hi}",
        )


def label_cactus(
    spline: ContourSpline,
    extrema: list[CurvatureExtremum],
    centre_u: float,
    hand_exclusion: float = 0.25,
    spacing_px: float = 0.5,
    leg_gap: np.ndarray | None = None,
) -> Labelling:
    """Label back, neck, shoulders and elbows on a posture-5 outline (rules in the module doc).

    Args:
        spline: the outline's spline (:func:`~torchfit.parts.curve.fit_contour_spline`).
        extrema: its significant extrema (:func:`~torchfit.parts.curve.curvature_extrema`).
        centre_u: ``u`` of the body's centre column, pixels (e.g. the silhouette's centroid).
        hand_exclusion: inner-elbow candidates higher than this many trunk lengths above the
            neck minimum belong to the hand and are skipped.
        spacing_px: outline sampling step for the extremities, pixels.
        leg_gap: ``(2,)`` the top of a hole between the legs, when the silhouette has one
            (see :func:`torchfit.parts.decompose.leg_gap_top`); it is then the crotch.

    Returns:
        A :class:`Labelling`; ``status == "failed"`` with ``failed_rule`` naming the rule when
        the outline does not show the expected posture.
    """
    result = Labelling(spline=spline, extrema=list(extrema), centre_u=float(centre_u))
    try:
        _run_rules(result, spline, extrema, centre_u, hand_exclusion, spacing_px, leg_gap)
    except RuleFailure as failure:
        return result.fail(failure)
    result.status = "ok"
    return result


def _run_rules(
    result: Labelling,
    spline: ContourSpline,
    extrema: list[CurvatureExtremum],
    centre_u: float,
    hand_exclusion: float,
    spacing_px: float,
    leg_gap: np.ndarray | None,
) -> None:
    t, pts = spline.sample(spacing_px)
    ext = _extremities(t, pts, centre_u)
    for name, value in ext.items():
        result.landmarks[name] = spline.point(value)[0]
    minima = [e for e in extrema if e.kind == "min"]
    maxima = [e for e in extrema if e.kind == "max"]

    def arc(a: str, b: str) -> _Arc:
        others = [v for k, v in ext.items() if k not in (a, b)]
        return _arc_between(ext[a], ext[b], others)

    # Back: the crotch, the highest minimum between the feet.
    inner = arc("l_foot", "r_foot")
    if leg_gap is not None:
        crotch_point = np.asarray(leg_gap, dtype=np.float64)
    else:
        on_inner = inner.contains(t)
        on_inner &= ~np.isclose(t, ext["l_foot"]) & ~np.isclose(t, ext["r_foot"])
        candidates = [e for e in minima if inner.contains(e.t)]
        if not candidates:
            raise RuleFailure("back", "no negative curvature minimum between the feet (no crotch)")
        # The apex of the arch between the legs; floor shadows on this arc lie lower.
        crotch_point = pts[on_inner][np.argmin(pts[on_inner, 1])]
    crotch = CurvatureExtremum(float("nan"), crotch_point.copy(), 0.0, "min")
    result.landmarks["crotch"] = crotch.point

    # Neck: shortest cut between a minimum of each top arc.
    top = {s: arc("head_top", f"{s}_hand") for s in "lr"}
    top_minima = {s: [e for e in minima if top[s].contains(e.t)] for s in "lr"}
    for s in "lr":
        if not top_minima[s]:
            raise RuleFailure("neck", f"no negative curvature minimum between head and {s} hand")
    pairs = [(a, b) for a in top_minima["l"] for b in top_minima["r"]]
    neck_l, neck_r = min(pairs, key=lambda p: float(np.linalg.norm(p[0].point - p[1].point)))
    neck_cut = Cut(neck_r.point.copy(), neck_l.point.copy())
    result.cuts["neck"] = neck_cut
    if not neck_cut.middle[1] < crotch.point[1]:
        raise RuleFailure("neck", "the neck cut is not above the crotch")

    # Principal axis, neck -> back (down the body); its length T scales the thresholds.
    trunk = float(np.linalg.norm(crotch.point - neck_cut.middle))
    height = float(np.ptp(pts[:, 1]))
    if not 0.15 * height < trunk < 0.6 * height:
        raise RuleFailure(
            "back",
            f"neck–crotch distance {trunk:.0f} px is not 0.15–0.6 of the height {height:.0f}",
        )
    _check_ratio("neck", "neck cut", neck_cut.length, trunk, 0.08, 0.5)
    neck_min = {"l": neck_l, "r": neck_r}

    joints: dict[str, np.ndarray] = {}
    anchors: dict[str, np.ndarray] = {}
    joints["back"] = crotch.point.copy()
    anchors["back"] = crotch.point[None].copy()
    joints["neck"] = neck_cut.middle
    anchors["neck"] = np.stack([neck_cut.a, neck_cut.b])

    for s in "lr":
        # Elbow: shortest cut from an inner-elbow minimum to an outer-arc maximum below it.
        outer = arc(f"{s}_hand", f"{s}_foot")
        highest = neck_min[s].point[1] - hand_exclusion * trunk
        inner_c = [
            e
            for e in top_minima[s]
            if e is not neck_min[s]
            and top[s].position(e.t) > top[s].position(neck_min[s].t)
            and e.point[1] > highest
        ]
        outer_c = [e for e in maxima if outer.contains(e.t)]
        pairs = [(a, b) for a in inner_c for b in outer_c if b.point[1] > a.point[1]]
        if not pairs:
            raise RuleFailure(
                "elbow",
                f"no {s} elbow: no inner minimum beyond the neck paired with an outer maximum "
                f"below it ({len(inner_c)} inner, {len(outer_c)} outer candidates)",
            )
        inner_e, outer_e = min(pairs, key=lambda p: float(np.linalg.norm(p[0].point - p[1].point)))
        elbow_cut = Cut(inner_e.point.copy(), outer_e.point.copy())
        result.cuts[f"{s}_elbow"] = elbow_cut
        _check_ratio("elbow", f"{s} elbow cut", elbow_cut.length, trunk, 0.05, 0.6)
        joints[f"{s}_elbow"] = elbow_cut.middle
        anchors[f"{s}_elbow"] = np.stack([elbow_cut.a, elbow_cut.b])

        # Shoulder: neck minimum -> armpit (outer arc, after the outer elbow, above the crotch).
        after = outer.position(outer_e.t)
        armpits = [
            e
            for e in minima
            if outer.contains(e.t)
            and outer.position(e.t) > after
            and e.point[1] < crotch.point[1]
            and e.point[1] > neck_min[s].point[1]
        ]
        if not armpits:
            raise RuleFailure("shoulder", f"no {s} armpit: no negative minimum below the {s} elbow")
        armpit = min(armpits, key=lambda e: float(np.linalg.norm(e.point - neck_min[s].point)))
        shoulder_cut = Cut(neck_min[s].point.copy(), armpit.point.copy())
        result.cuts[f"{s}_shoulder"] = shoulder_cut
        _check_ratio("shoulder", f"{s} shoulder cut", shoulder_cut.length, trunk, 0.1, 0.8)
        joints[f"{s}_shoulder"] = shoulder_cut.middle
        anchors[f"{s}_shoulder"] = np.stack([shoulder_cut.a, shoulder_cut.b])
    result.raw_joints = joints
    result.joints = {k: v.copy() for k, v in joints.items()}
    result.anchors = anchors
