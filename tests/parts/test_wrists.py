"""Tests of torchfit.parts.wrists: skin model, hand ellipse and wrist on a drawn figure.

Reference: a synthetic cactus figure drawn with cv2 whose face and hands are filled with a
noisy skin colour and whose clothes are blue. A hand is a disc of known centre ``c`` and
radius ``r``; the second moments of a uniform disc are ``r^2 / 4`` per axis, so its ellipse
(semi-axes ``2 sigma``) is the disc itself and the wrist is ``c - r * unit(c - elbow)``.
Mahalanobis distances and ellipse boundaries are checked against numpy formulas.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from torchfit.config import PartsConfig
from torchfit.parts.decompose import decompose_cactus
from torchfit.parts.rules import Cut, Labelling, RuleFailure
from torchfit.parts.wrists import (
    Ellipse,
    SkinModel,
    find_wrists,
    hand_ellipse,
    skin_model_from_face,
)

SKIN = (215, 160, 130)
CLOTH = (40, 60, 170)
HAND_R = 12
# posture-5 stick figure (u, v): person's left on the image right
J = {
    "head": (200, 60),
    "l_elbow": (300, 125),
    "r_elbow": (100, 125),
    "l_hand": (300, 55),  # hand disc centres
    "r_hand": (100, 55),
}


def _figure(hand_colour=SKIN, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) uint8 RGB image and (H, W) bool silhouette of a clothed cactus figure."""
    rng = np.random.default_rng(seed)
    colour = np.zeros((400, 400), np.uint8)  # 0 background, 1 cloth, 2 skin, 3 hand
    cv2.circle(colour, J["head"], 22, 2, -1)
    cv2.line(colour, (200, 80), (200, 105), 2, 16)  # neck (skin)
    cv2.rectangle(colour, (172, 120), (228, 245), 1, -1)  # trunk
    for s in "lr":
        cv2.line(colour, (200, 125), J[f"{s}_elbow"], 1, 22)  # upper arm
        cv2.line(colour, J[f"{s}_elbow"], (J[f"{s}_hand"][0], 70), 1, 18)  # sleeve
        cv2.circle(colour, J[f"{s}_hand"], HAND_R, 3, -1)
        hip = (185 if s == "r" else 215, 240)
        cv2.line(colour, hip, (235 if s == "l" else 165, 370), 1, 28)
    # rounded like a real outline (the rules need a neck concavity, as in test_parts' cactus)
    mask = cv2.GaussianBlur((colour > 0).astype(np.float32), (0, 0), 1.5) > 0.5
    colour[mask & (colour == 0)] = 1
    colour[~mask] = 0
    image = np.full((400, 400, 3), 128, np.uint8)
    for value, rgb in ((1, CLOTH), (2, SKIN), (3, hand_colour)):
        sel = colour == value
        noise = rng.normal(0, 4, size=(int(sel.sum()), 3))
        image[sel] = np.clip(np.array(rgb) + noise, 0, 255).astype(np.uint8)
    return image, mask


def _labelling() -> Labelling:
    """An ``ok`` labelling with what find_wrists reads: neck cut, head top, hands, elbows."""
    lab = Labelling(status="ok")
    lab.cuts["neck"] = Cut(np.array([190.0, 100.0]), np.array([210.0, 100.0]))
    lab.landmarks["head_top"] = np.array([200.0, 38.0])
    for s in "lr":
        u, v = J[f"{s}_hand"]
        lab.landmarks[f"{s}_hand"] = np.array([u, v - HAND_R], float)  # the hand's top
        lab.raw_joints[f"{s}_elbow"] = np.array(J[f"{s}_elbow"], float)
    return lab


def test_skin_model_and_mahalanobis_distance():
    image, mask = _figure()
    skin = skin_model_from_face(image, mask, _labelling())
    assert isinstance(skin, SkinModel)
    # face pixels: 100 > v > 100 - 0.45 * 62 = 72.1, 190 <= u <= 210, inside the silhouette
    vv, uu = np.nonzero(mask)
    sel = (vv < 100) & (vv > 72.1) & (uu >= 190) & (uu <= 210)
    assert skin.n_pixels == int(sel.sum())
    rgb = image[vv[sel], uu[sel]].astype(float)
    chroma = rgb[:, :2] / rgb.sum(1, keepdims=True)
    np.testing.assert_allclose(skin.mean, chroma.mean(0), rtol=1e-12)
    np.testing.assert_allclose(skin.cov, np.cov(chroma.T) + 1e-5 * np.eye(2), rtol=1e-12)
    np.testing.assert_allclose(skin.mean, np.array(SKIN[:2]) / sum(SKIN), atol=2e-3)
    # distance: sqrt((c - m)^T C^-1 (c - m)) per pixel; skin close, cloth far
    px = np.array([SKIN, CLOTH, (0, 0, 0)], float)
    c = np.array([[p[0] / max(p.sum(), 1), p[1] / max(p.sum(), 1)] for p in px])
    ref = [float(np.sqrt((x - skin.mean) @ np.linalg.inv(skin.cov) @ (x - skin.mean))) for x in c]
    np.testing.assert_allclose(skin.distance(px), ref, rtol=1e-10)
    assert ref[0] < 1.0 < 3.0 < ref[1]


def test_ellipse_boundary_and_axes():
    cov = np.array([[9.0, 0.0], [0.0, 4.0]])  # sigma 3 along u, 2 along v
    e = Ellipse(np.array([10.0, 20.0]), cov, 100)
    np.testing.assert_allclose(e.boundary_towards(np.array([50.0, 20.0])), [16.0, 20.0])
    np.testing.assert_allclose(e.boundary_towards(np.array([10.0, 0.0])), [10.0, 16.0])
    p = e.boundary_towards(np.array([13.0, 24.0]))  # oblique: on the ellipse, on the ray
    d = p - e.centre
    assert d @ np.linalg.solve(cov, d) == pytest.approx(4.0)
    assert d[0] * 4.0 - d[1] * 3.0 == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(e.boundary_towards(e.centre), e.centre)
    major, minor, angle = e.axes()
    assert (major, minor) == pytest.approx((6.0, 4.0))
    assert angle % 180.0 == pytest.approx(0.0)
    rot = Ellipse(np.zeros(2), np.array([[4.0, 0.0], [0.0, 9.0]]), 1)
    assert rot.axes()[2] % 180.0 == pytest.approx(90.0)


def test_hand_ellipse_is_the_drawn_hand():
    image, mask = _figure()
    skin = skin_model_from_face(image, mask, _labelling())
    elbow = np.array(J["l_elbow"], float)
    tip = np.array([300.0, 55.0 - HAND_R])
    e = hand_ellipse(image, mask, elbow, tip, skin)
    disc = np.zeros_like(mask, np.uint8)
    cv2.circle(disc, J["l_hand"], HAND_R, 1, -1)
    assert e.n_pixels == int((disc.astype(bool) & mask).sum())
    np.testing.assert_allclose(e.centre, J["l_hand"], atol=0.05)
    major, minor, _ = e.axes()
    assert major == pytest.approx(HAND_R, abs=0.6) and minor == pytest.approx(HAND_R, abs=0.6)


def test_find_wrists_places_the_wrist_where_the_hand_meets_the_forearm():
    image, mask = _figure()
    lab = _labelling()
    hands = find_wrists(image, mask, lab)
    assert set(hands) == {"l_hand", "r_hand"}
    for s in "lr":
        c = np.array(J[f"{s}_hand"], float)
        elbow = np.array(J[f"{s}_elbow"], float)
        expected = c + HAND_R * (elbow - c) / np.linalg.norm(elbow - c)  # (u, 67)
        np.testing.assert_allclose(lab.raw_joints[f"{s}_wrist"], expected, atol=1.0)
        np.testing.assert_allclose(lab.joints[f"{s}_wrist"], lab.raw_joints[f"{s}_wrist"])
        np.testing.assert_allclose(lab.anchors[f"{s}_wrist"], lab.raw_joints[f"{s}_wrist"][None])
        assert lab.anchors[f"{s}_wrist"].shape == (1, 2)


def test_no_skin_at_the_hands_raises_a_wrist_rule_failure():
    image, mask = _figure(hand_colour=CLOTH)  # gloves the colour of the sleeves
    with pytest.raises(RuleFailure, match=r"^wrist: only 0 skin-coloured pixels at the hand$"):
        find_wrists(image, mask, _labelling())
    with pytest.raises(RuleFailure, match="elbow and hand tip coincide") as info:
        hand_ellipse(image, mask, np.array([300.0, 125.0]), np.array([300.5, 125.0]), None)
    assert info.value.rule == "wrist"
    # no face below the head top: nothing to learn the skin colour from
    lab = _labelling()
    lab.landmarks["head_top"] = np.array([200.0, 99.0])
    with pytest.raises(RuleFailure, match=r"wrist: too few face pixels \(0\)"):
        find_wrists(image, mask, lab)


def test_decompose_reports_the_wrist_rule_when_the_hands_are_not_skin():
    image, mask = _figure()
    ok = decompose_cactus(mask, image, PartsConfig())
    assert ok.ok, ok.message
    for s in "lr":
        c = np.array(J[f"{s}_hand"], float)
        assert np.linalg.norm(ok.raw_joints[f"{s}_wrist"] - c) == pytest.approx(HAND_R, abs=2.0)
        assert abs(ok.raw_joints[f"{s}_wrist"][0] - c[0]) < 2.0
    gloved, mask = _figure(hand_colour=CLOTH)
    failed = decompose_cactus(mask, gloved, PartsConfig())
    assert failed.status == "failed" and failed.failed_rule == "wrist"
    assert "skin-coloured" in failed.message
    assert failed.joints == {} and failed.raw_joints == {}
    # without the wrists the same figure labels fine
    assert decompose_cactus(mask, gloved, PartsConfig(wrists=False)).ok
