"""benchmarks/span_depth.py: the T-pose width and the fitted depth of a subject whose answers
are known by construction (a camera looking along the world's y axis, a rectangle as the
T-pose silhouette)."""

import json

import cv2
import numpy as np
import pytest
import yaml
from scripts import load_script

FOCAL = 500.0
DEPTH = 3.0  # the joints' depth along the camera axis


@pytest.fixture(scope="module")
def tool():
    return load_script("benchmarks/span_depth.py")


def _subject(root, width_px, span_m, root_y):
    """A subject folder with its truth and a fitted run's params and measurements."""
    root.mkdir()
    # world y is the camera's depth: x_cam = x, y_cam = -(z - 1), z_cam = y + DEPTH
    camera = {
        "image_size": [640, 480],
        "K": [[FOCAL, 0, 320], [0, FOCAL, 240], [0, 0, 1]],
        "dist": [0, 0, 0, 0, 0],
        "R": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
        "t": [0, 1, DEPTH],
    }
    (root / "camera.yaml").write_text(yaml.safe_dump(camera))
    joints = {
        name: [x, 0.0, 1.4]
        for name, x in (
            ("l_wrist", -0.7),
            ("r_wrist", 0.7),
            ("l_shoulder", -0.2),
            ("r_shoulder", 0.2),
        )
    }
    joints["back"] = [0.0, 0.0, 0.9]
    truth = {"arm_span_m": span_m, "height_m": 1.75, "joints_world": {"pose4": joints}}
    (root / "truth.json").write_text(json.dumps(truth))
    (root / "truth_masks").mkdir()
    mask = np.zeros((480, 640), np.uint8)
    mask[100:300, 100 : 100 + width_px] = 255
    cv2.imwrite(str(root / "truth_masks" / "pose4.png"), mask)
    return {
        "params": {"poses": {"pose4": {"root_translation_xy": [0.0, root_y]}}},
        "measurements": {"arm_span_m": 1.02 * span_m},
    }


def test_the_figures_of_a_known_subject(tool, tmp_path):
    # 300 px at 3 m with f = 500 px is 1.8 m: the image shows the span exactly
    fitted = _subject(tmp_path / "s", 300, 1.8, root_y=-0.06)
    row = tool.subject_row(tmp_path / "s", fitted)
    assert row["span"] == pytest.approx(2.0)
    assert row["image"] == pytest.approx(0.0, abs=1e-9)
    # the fitted root 6 cm nearer the camera than the back: 2 % short of its depth
    assert row["depth"] == pytest.approx(-2.0)
    assert row["ratio"] == pytest.approx(1.8 / 1.75)


def test_a_wider_silhouette_shows_a_longer_span(tool, tmp_path):
    fitted = _subject(tmp_path / "s", 303, 1.8, root_y=0.0)
    row = tool.subject_row(tmp_path / "s", fitted)
    assert row["image"] == pytest.approx(1.0)
    assert row["depth"] == pytest.approx(0.0, abs=1e-9)
