"""A bent joint's pixel from its limbs' axes (torchfit.image.bends).

The reference is geometry: two thick bands drawn with OpenCV along known centre lines, whose
crossing is computed by hand beside each test.
"""

import math

import cv2
import numpy as np
import pytest

from torchfit.errors import ShapeError
from torchfit.fit.bends import bend_target
from torchfit.image.bends import crossing, limb_axis


def bend_point(mask: np.ndarray, *joints) -> np.ndarray | None:
    """The crossing's pixel, or None where :func:`crossing` finds none."""
    found = crossing(mask, *joints)
    return None if found is None else found.point


def _band(mask: np.ndarray, a, b, width: int) -> None:
    """Draw a band of ``width`` pixels along the centre line a -> b (pixel centres)."""
    shift = 4  # sub-pixel end points
    pa = tuple(int(round(c * 2**shift)) for c in a)
    pb = tuple(int(round(c * 2**shift)) for c in b)
    cv2.line(mask, pa, pb, 1, width, cv2.LINE_8, shift)


def _crossing(p1, d1, p2, d2) -> np.ndarray:
    """The crossing of the lines p1 + s d1 and p2 + t d2, by Cramer's rule."""
    det = d1[0] * (-d2[1]) - d1[1] * (-d2[0])
    rx, ry = p2[0] - p1[0], p2[1] - p1[1]
    s = (rx * (-d2[1]) - ry * (-d2[0])) / det
    return np.array([p1[0] + s * d1[0], p1[1] + s * d1[1]])


@pytest.mark.parametrize("angle_deg", [90.0, 60.0, 120.0])
def test_the_crossing_of_two_bands_is_found(angle_deg):
    # a thigh hanging down from the hip, a shank leaving the knee at angle_deg from it
    mask = np.zeros((300, 300), np.uint8)
    hip, knee = (150.0, 40.0), (150.0, 150.0)
    turn = math.radians(angle_deg)
    ankle = (knee[0] + 110 * math.sin(turn), knee[1] + 110 * -math.cos(turn))
    _band(mask, hip, knee, 31)
    _band(mask, knee, ankle, 21)
    found = bend_point(mask.astype(bool), np.array(hip), np.array(knee), np.array(ankle))
    assert found is not None
    truth = _crossing(hip, (0.0, 1.0), knee, (math.sin(turn), -math.cos(turn)))
    np.testing.assert_allclose(found, truth, atol=1.0)


def test_guesses_a_few_pixels_off_find_the_same_crossing():
    mask = np.zeros((300, 300), np.uint8)
    _band(mask, (150.0, 40.0), (150.0, 150.0), 31)
    _band(mask, (150.0, 150.0), (260.0, 150.0), 21)
    exact = bend_point(mask.astype(bool), *map(np.array, [(150, 40), (150, 150), (260, 150)]))
    moved = bend_point(mask.astype(bool), *map(np.array, [(155, 44), (146, 157), (262, 146)]))
    assert exact is not None and moved is not None
    np.testing.assert_allclose(moved, exact, atol=1.0)
    np.testing.assert_allclose(exact, [150.0, 150.0], atol=1.0)


def test_a_straight_limb_marks_no_bend():
    mask = np.zeros((300, 300), np.uint8)
    _band(mask, (150.0, 20.0), (150.0, 280.0), 25)
    guesses = [np.array(p, float) for p in [(150, 20), (150, 150), (152, 280)]]
    assert bend_point(mask.astype(bool), *guesses) is None
    # the axis itself is found, straight down
    axis = limb_axis(mask.astype(bool), guesses[0], guesses[1], (0.3, 0.7))
    assert axis is not None
    np.testing.assert_allclose(np.abs(axis[1]), [0.0, 1.0], atol=1e-6)


def test_the_sections_a_bite_spoils_are_left_out_of_the_axis():
    # a thigh the segmentation lost half of over its upper part: two of the nine sections
    # are half as wide, their midpoints off the band's centre line; the other seven hold it
    mask = np.zeros((300, 300), np.uint8)
    _band(mask, (150.0, 40.0), (150.0, 150.0), 31)
    _band(mask, (150.0, 150.0), (260.0, 150.0), 21)
    whole = bend_point(mask.astype(bool), *map(np.array, [(150, 40), (150, 150), (260, 150)]))
    mask[40:82, 150:170] = 0
    hip, knee, ankle = (np.array(p, float) for p in [(150, 40), (150, 150), (260, 150)])
    axis = limb_axis(mask.astype(bool), hip, knee, (0.3, 0.75))
    assert axis is not None
    np.testing.assert_allclose(axis[0][0], 150.0, atol=0.5)
    np.testing.assert_allclose(axis[1], [0.0, 1.0], atol=1e-3)
    found = bend_point(mask.astype(bool), hip, knee, ankle)
    assert whole is not None and found is not None
    np.testing.assert_allclose(found, whole, atol=0.5)


def test_a_band_with_more_than_two_sections_spoilt_is_not_an_axis():
    # four of the nine sections bitten: not a band with a few bad sections any more
    mask = np.zeros((300, 300), np.uint8)
    _band(mask, (150.0, 40.0), (150.0, 150.0), 31)
    _band(mask, (150.0, 150.0), (260.0, 150.0), 21)
    mask[40:95, 150:170] = 0
    hip, knee, ankle = (np.array(p, float) for p in [(150, 40), (150, 150), (260, 150)])
    assert limb_axis(mask.astype(bool), hip, knee, (0.3, 0.75)) is None
    assert bend_point(mask.astype(bool), hip, knee, ankle) is None


def test_a_band_mostly_spoilt_is_not_trusted_against_the_model():
    # the bite reaches over seven of the nine sections: what is left is a straight band half
    # as wide, a limb of its own to the image; the model's band at the same place is not
    whole = np.zeros((300, 300), np.uint8)
    _band(whole, (150.0, 40.0), (150.0, 150.0), 31)
    _band(whole, (150.0, 150.0), (260.0, 150.0), 21)
    spoilt = whole.copy()
    spoilt[40:112, 150:170] = 0
    joints = np.array([(150, 40), (150, 150), (260, 150)], float)
    axis = limb_axis(spoilt.astype(bool), joints[0], joints[1], (0.3, 0.75))
    assert axis is not None and axis.width == pytest.approx(16, abs=1.5)
    assert limb_axis(whole.astype(bool), joints[0], joints[1], (0.3, 0.75)).width > 30
    args = (15.0, 30.0, 1.5)
    assert bend_target(spoilt.astype(bool), whole.astype(bool), joints, *args) is None
    same = bend_target(whole.astype(bool), whole.astype(bool), joints, *args)
    np.testing.assert_allclose(same, joints[1], atol=1e-9)


def test_a_section_off_the_line_is_left_out():
    # a hand against the thigh at one section: a run as wide as the band, shifted sideways
    mask = np.zeros((300, 300), np.uint8)
    _band(mask, (150.0, 40.0), (150.0, 150.0), 31)
    mask[96:100, 135:141] = 0  # the band's left edge cut back at one section ...
    mask[96:100, 166:172] = 1  # ... and grown on the right: same width, midpoint 6 px off
    hip, knee = np.array([150.0, 40.0]), np.array([150.0, 150.0])
    axis = limb_axis(mask.astype(bool), hip, knee, (0.3, 0.75))
    assert axis is not None
    np.testing.assert_allclose(axis[0][0], 150.0, atol=0.5)
    np.testing.assert_allclose(axis[1], [0.0, 1.0], atol=1e-3)


def test_a_limb_the_image_frame_cuts_is_not_measured():
    # a thigh across the picture to a knee near its right border, the shank going up
    hip, knee, ankle = (np.array(p, float) for p in [(40, 100), (170, 100), (170, 0)])
    inside = np.zeros((200, 230), np.uint8)
    _band(inside, hip, knee, 31)
    _band(inside, knee, ankle, 31)
    assert bend_point(inside.astype(bool), hip, knee, ankle) is not None
    # the same limbs in a picture whose right border cuts the shank across its width
    cut = np.ascontiguousarray(inside[:, :180])
    assert bend_point(cut.astype(bool), hip, knee, ankle) is None


def test_a_mask_of_the_wrong_shape_is_refused():
    with pytest.raises(ShapeError, match=r"mask: expected \(H, W\)"):
        limb_axis(np.zeros((1, 10, 10), bool), np.zeros(2), np.ones(2) * 9, (0.3, 0.7))
