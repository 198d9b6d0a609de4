"""What the part rules produce: cuts, joints and their systematic offsets, the labelling and
its failure (see :mod:`torchfit.parts.rules`). Pixels ``(u, v)``, ``v`` down."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from torchfit.parts.curve import ContourSpline, CurvatureExtremum

__all__ = ["RULE_NAMES", "RuleFailure", "Cut", "JointOffsets", "Labelling", "joint_kind"]

#: The rules in the order they run; a failed labelling names one of them.
RULE_NAMES: tuple[str, ...] = ("extremities", "back", "neck", "elbow", "shoulder", "wrist")


class RuleFailure(Exception):
    """Raised inside the rules when one of them finds nothing (caught by the callers)."""

    def __init__(self, rule: str, message: str) -> None:
        super().__init__(f"{rule}: {message}")
        self.rule = rule
        self.message = message


@dataclass
class Cut:
    """A straight cut between two outline points.

    Attributes:
        a, b: ``(2,)`` end points, ``(u, v)`` pixels.
    """

    a: np.ndarray
    b: np.ndarray

    @property
    def middle(self) -> np.ndarray:
        """``(2,)`` the middle of the cut."""
        return 0.5 * (self.a + self.b)

    @property
    def length(self) -> float:
        """Length in pixels."""
        return float(np.linalg.norm(self.b - self.a))

    def at(self, fraction: float) -> np.ndarray:
        """``(2,)`` the point ``a + fraction (b - a)``."""
        return self.a + fraction * (self.b - self.a)


@dataclass
class JointOffsets:
    """Systematic corrections from cut points to joint centres (all zero: the paper's points).

    Each joint moves by ``(down, out)`` times the 2-D trunk length ``T = |neck cut middle -
    crotch|`` (so they scale with the person's image size): ``down`` along the principal axis
    (towards the back), ``out`` away from it on the joint's side (ignored for back and neck).
    For example the pelvis (hip joint centres) lies above the crotch (``back[0] < 0``), and the
    glenohumeral centre lies outside and below the middle of the neck–armpit cut.

    Attributes:
        back, neck, shoulder, elbow, wrist: ``(down, out)`` in units of ``T``.
    """

    back: tuple[float, float] = (0.0, 0.0)
    neck: tuple[float, float] = (0.0, 0.0)
    shoulder: tuple[float, float] = (0.0, 0.0)
    elbow: tuple[float, float] = (0.0, 0.0)
    wrist: tuple[float, float] = (0.0, 0.0)

    def apply(self, labelling: Labelling) -> None:
        """Move the joints of an ``ok`` labelling in place (its ``raw_joints`` keep the cut
        points)."""
        down, outward, trunk = labelling.body_frame()
        for name, point in labelling.raw_joints.items():
            d, o = getattr(self, joint_kind(name))
            side = _side(name, outward)
            labelling.joints[name] = point + trunk * (d * down + o * side)

    @staticmethod
    def measure(labelling: Labelling, name: str, target: np.ndarray) -> tuple[float, float]:
        """The ``(down, out)`` offset, in units of ``T``, that would move joint ``name``'s cut
        point onto the pixel ``target`` (the inverse of :meth:`apply` for one joint)."""
        down, outward, trunk = labelling.body_frame()
        delta = (np.asarray(target, dtype=float) - labelling.raw_joints[name]) / trunk
        return float(delta @ down), float(delta @ _side(name, outward))


def joint_kind(name: str) -> str:
    """``"l_elbow"`` -> ``"elbow"``; ``"neck"`` -> ``"neck"`` (the :class:`JointOffsets` field)."""
    return name.split("_", 1)[-1]


def _side(name: str, outward: dict[str, np.ndarray]) -> np.ndarray:
    """The outward unit vector of a left/right joint; zero for back and neck."""
    return outward.get(name[0], np.zeros(2)) if "_" in name else np.zeros(2)


@dataclass
class Labelling:
    """Joints found on one posture-5 silhouette.

    Attributes:
        status: ``"ok"`` or ``"failed"``.
        failed_rule: the rule that failed (one of :data:`RULE_NAMES`), None when ok.
        message: why it failed ("" when ok).
        joints: joint name -> ``(2,)`` ``(u, v)`` pixels: ``back``, ``neck``, ``l_shoulder``,
            ``r_shoulder``, ``l_elbow``, ``r_elbow`` (and ``l_wrist``, ``r_wrist`` once
            :mod:`torchfit.parts.wrists` has run). Empty when failed.
        cuts: ``"neck"``, ``"l_shoulder"``, ``"r_shoulder"``, ``"l_elbow"``, ``"r_elbow"`` ->
            :class:`Cut` (whatever was found before a failure).
        landmarks: ``head_top``, ``l_hand``, ``r_hand``, ``l_foot``, ``r_foot``, ``crotch`` ->
            ``(2,)`` pixels (whatever was found).
        spline: the contour spline, None when no contour was found.
        extrema: the significant curvature extrema used.
        raw_joints: the joints before :class:`JointOffsets` (cut middles, crotch, wrists).
        anchors: joint name -> ``(K, 2)`` outline points the joint was built from (cut ends,
            the crotch, the wrist itself); the stereo matcher measures disparities there.
        hands: ``"l_hand"``, ``"r_hand"`` -> :class:`torchfit.parts.wrists.Ellipse` once the
            wrists were found.
        centre_u: ``u`` of the centre column used, pixels.
    """

    status: str = "failed"
    failed_rule: str | None = None
    message: str = ""
    joints: dict[str, np.ndarray] = field(default_factory=dict)
    cuts: dict[str, Cut] = field(default_factory=dict)
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)
    spline: ContourSpline | None = None
    extrema: list[CurvatureExtremum] = field(default_factory=list)
    raw_joints: dict[str, np.ndarray] = field(default_factory=dict)
    anchors: dict[str, np.ndarray] = field(default_factory=dict)
    hands: dict = field(default_factory=dict)
    centre_u: float = float("nan")

    def body_frame(self) -> tuple[np.ndarray, dict[str, np.ndarray], float]:
        """The principal axis frame: ``(down (2,), {"l": out (2,), "r": out (2,)}, T)``."""
        axis = self.landmarks["crotch"] - self.cuts["neck"].middle
        trunk = float(np.linalg.norm(axis))
        down = axis / trunk
        right = np.array([-down[1], down[0]])
        if right[0] < 0:
            right = -right
        return down, {"l": right, "r": -right}, trunk

    @property
    def ok(self) -> bool:
        """True when every rule succeeded."""
        return self.status == "ok"

    def fail(self, failure: RuleFailure) -> Labelling:
        """Mark as failed by ``failure`` and drop the joints (never a partial labelling)."""
        self.status = "failed"
        self.failed_rule = failure.rule
        self.message = failure.message
        self.joints = {}
        self.raw_joints = {}
        return self


# --------------------------------------------------------------------------------------------
# Arcs of the periodic parameter
