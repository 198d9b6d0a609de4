"""benchmarks/span_depth.py: the T-pose width and the fitted depth of a subject whose answers
are known by construction (a camera looking along the world's y axis, a rectangle as the
T-pose silhouette, the truth's joints those of the template body the "fit" reports)."""

import json
import math

import cv2
import numpy as np
import pytest
import yaml
from scripts import load_script

FOCAL = 500.0
DEPTH = 3.0  # the camera's distance from the world origin, along world y


@pytest.fixture(scope="module")
def tool():
    return load_script("benchmarks/span_depth.py")


def _params(model, root_y):
    """A params.json record: the template's own scales in the T-pose, ``root_y`` along y."""
    angles = {f"{side}_shoulder_abduct": math.pi / 2 for side in "lr"}
    pose = {
        "joint_angles": angles,
        "root_rotation": np.eye(3).tolist(),
        "root_translation_xy": [0.0, root_y],
    }
    scales = {name: [1.0, 1.0, 1.0] for name in model.template.segments}
    return {"template": "mpeg4_full", "segment_scales": scales, "poses": {"pose4": pose}}


def _subject(tool, root, model, width_px, span_m):
    """A subject folder whose true T-pose joints are the template's at the origin."""
    root.mkdir()
    # x_cam = x, y_cam = 1 - z, z_cam = y + DEPTH
    camera = {
        "image_size": [640, 480],
        "K": [[FOCAL, 0, 320], [0, FOCAL, 240], [0, 0, 1]],
        "dist": [0, 0, 0, 0, 0],
        "R": [[1, 0, 0], [0, 0, -1], [0, 1, 0]],
        "t": [0, 1, DEPTH],
    }
    (root / "camera.yaml").write_text(yaml.safe_dump(camera))
    posed = tool.posed_joints(model, _params(model, 0.0), "pose4")
    joints = {k: posed[k].tolist() for k in ("l_hip", "r_hip", "l_shoulder", "r_shoulder")}
    joints.update({k: posed[k].tolist() for k in ("l_wrist", "r_wrist")})
    truth = {"arm_span_m": span_m, "height_m": 1.75, "joints_world": {"pose4": joints}}
    (root / "truth.json").write_text(json.dumps(truth))
    (root / "truth_masks").mkdir()
    mask = np.zeros((480, 640), np.uint8)
    mask[100:300, 100 : 100 + width_px] = 255
    cv2.imwrite(str(root / "truth_masks" / "pose4.png"), mask)
    return joints


def _torso_depth(joints):
    return np.mean([joints[k][1] + DEPTH for k in ("l_hip", "r_hip", "l_shoulder", "r_shoulder")])


def test_the_figures_of_a_known_subject(tool, model, tmp_path):
    joints = _subject(tool, tmp_path / "s", model, 300, 1.8)
    # the image: 300 px at the arms' true depth over f = 500 px, against a span of 1.8 m
    arms = np.mean(
        [joints[k][1] + DEPTH for k in ("l_wrist", "r_wrist", "l_shoulder", "r_shoulder")]
    )
    fitted = {"params": _params(model, -0.06), "measurements": {"arm_span_m": 1.02 * 1.8}}
    row = tool.subject_row(tmp_path / "s", fitted, model)
    assert row["span"] == pytest.approx(2.0)
    assert row["image"] == pytest.approx(100 * (300 * arms / FOCAL / 1.8 - 1))
    # the fitted body 6 cm nearer the camera than the true one
    depth = _torso_depth(joints)
    assert row["depth"] == pytest.approx(100 * ((depth - 0.06) / depth - 1))
    assert row["ratio"] == pytest.approx(1.8 / 1.75)


def test_the_fitted_pose_stands_where_the_truth_does(tool, model, tmp_path):
    _subject(tool, tmp_path / "s", model, 303, 1.8)
    fitted = {"params": _params(model, 0.0), "measurements": {"arm_span_m": 1.8}}
    row = tool.subject_row(tmp_path / "s", fitted, model)
    assert row["depth"] == pytest.approx(0.0, abs=1e-9)
    assert row["span"] == pytest.approx(0.0, abs=1e-9)


def test_posed_joints_are_the_fits_own(tool, model, tmp_path):
    """A params.json record made by the pipeline gives back the fit's posed joints."""
    import torch
    from template_subjects import make_template_subject, segment_subjects

    from torchfit.camera import stack_cameras
    from torchfit.fit import SilhouetteFit, person_data_from_masks
    from torchfit.io.dataset import load_subject
    from torchfit.pipeline.outputs import pose_record

    make_template_subject(tmp_path / "s", model, scale=1.03, seed=3)
    subject = load_subject(tmp_path / "s")
    person = person_data_from_masks(segment_subjects([subject]), stack_cameras([subject.camera]))
    fit = SilhouetteFit(model, person)
    g = torch.Generator().manual_seed(11)
    x = fit.initial_params() + 0.05 * torch.randn(
        1, fit.num_params, generator=g, dtype=torch.float64
    )
    scales = model.expand_scales(fit.layout.group_scales(x))[0]
    params = {
        "segment_scales": dict(zip(model.template.segments, scales.tolist(), strict=True)),
        "poses": {"pose4": pose_record(fit, x, 0, 4)},
    }
    posed = tool.posed_joints(model, params, "pose4")
    _, origins = fit.pose_world(x, 4, torch.tensor([0]))
    for name in ("l_hip", "r_shoulder", "l_wrist"):
        expected = origins[0, model.template.joints[name]].numpy()
        np.testing.assert_allclose(posed[name], expected, atol=1e-9)
