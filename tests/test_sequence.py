"""Test sequences from real motion (tools/make_sequence.py) and tracking them end to end
(tools/track.py); anny generation makes these slow."""

import csv
import importlib.util
import json
import os
from pathlib import Path

import numpy as np
import pytest

from torchfit.io.bvh import read_bvh
from torchfit.synth.mocap import load_mocap, retarget

REPO = Path(__file__).resolve().parents[1]
CMU = Path(os.environ.get("TORCHFIT_SHARED", REPO / ".." / "shared")) / "data" / "cmu-mocap-sample"
needs_cmu = pytest.mark.skipif(not (CMU / "01_01.bvh").is_file(), reason="no shared CMU data")


def _tool(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@needs_cmu
def test_asf_amc_and_bvh_give_the_same_frames():
    """01_01 as ASF/AMC and as BVH: the BVH file has one more frame, the skeleton's rest pose
    first, which is not kept; then both count the same frames, and the leg joints agree in
    every one."""
    amc = load_mocap(CMU / "01_01.amc")
    bvh = load_mocap(CMU / "01_01.bvh")
    assert (bvh.skipped, amc.skipped) == (1, 0)
    assert bvh.num_frames == amc.num_frames == 2751
    for name in ("l_hip", "l_knee", "l_ankle", "r_knee", "l_toe", "r_toe"):
        gap = np.linalg.norm(amc.joints[name] - bvh.joints[name], axis=-1).max()
        assert gap < 0.02, (name, gap)


def test_a_rest_pose_before_the_motion_is_not_kept():
    """A first frame the limbs jump away from (a T-pose before the capture) is dropped; a
    clip whose first frame is its motion's, even one that starts with a fast move, is kept."""
    from torchfit.synth.mocap import _rest_pose_first

    rng = np.random.default_rng(0)
    walk = np.cumsum(rng.normal(0, 0.003, (200, 16, 3)), axis=0)  # a few mm a frame
    names = [f"j{i}" for i in range(15)] + ["back"]
    joints = {n: walk[:, i] for i, n in enumerate(names)}
    assert not _rest_pose_first(joints)
    kick = {n: v.copy() for n, v in joints.items()}
    kick["j3"][1:] += 0.06  # a hand 6 cm on at once (7 m/s at 120 Hz): motion
    assert not _rest_pose_first(kick)
    rest = {n: v.copy() for n, v in joints.items()}
    rest["j3"][0] += np.array([0.0, 0.6, 0.3])  # an arm out sideways, one frame
    assert _rest_pose_first(rest)
    assert not _rest_pose_first({n: v[:2] for n, v in rest.items()})  # too short to tell


@needs_cmu
def test_retarget_keeps_the_limb_directions():
    clip = load_mocap(CMU / "11_01.amc")
    joints = {k: v[300] for k, v in clip.joints.items()}
    frame, local = retarget(joints)
    np.testing.assert_allclose(frame.T @ frame, np.eye(3), atol=1e-9)
    down = np.array([0.0, 0.0, -1.0])
    upper = local["l_thigh"]
    lower = upper @ local["l_shank"]
    for rot, (a, b) in ((upper, ("l_hip", "l_knee")), (lower, ("l_knee", "l_ankle"))):
        want = frame.T @ (joints[b] - joints[a])
        np.testing.assert_allclose(rot @ down, want / np.linalg.norm(want), atol=1e-6)


@needs_cmu
def test_retarget_points_the_feet_along_the_capture():
    """With the body's neutral foot directions, each foot's ankle->toe line turns onto the
    capture's ankle->toe-base line; without them the feet are left alone."""
    clip = load_mocap(CMU / "01_01.bvh")
    neutral = {"l": np.array([0.0, -0.96, -0.28]), "r": np.array([0.0, -0.96, -0.28])}
    neutral = {k: v / np.linalg.norm(v) for k, v in neutral.items()}
    for index in (300, 420, 1500):  # standing, the jump's take-off, later
        joints = {k: v[index] for k, v in clip.joints.items()}
        frame, local = retarget(joints, neutral)
        for side in ("l", "r"):
            foot = local[f"{side}_thigh"] @ local[f"{side}_shank"] @ local[f"{side}_foot"]
            want = joints[f"{side}_toe"] - joints[f"{side}_ankle"]
            np.testing.assert_allclose(
                frame @ foot @ neutral[side], want / np.linalg.norm(want), atol=1e-9
            )
        assert "l_foot" not in retarget(joints)[1]


@pytest.mark.slow
@needs_cmu
def test_make_sequence_and_track_it(tmp_path):
    bvhio = pytest.importorskip("bvhio")
    out = tmp_path / "clip"
    args = ["--bvh", str(CMU / "01_01.bvh"), "--out", str(out), "--frames", "4"]
    args += ["--start", "300", "--step", "4", "--seed", "5", "--set", "image_size=[360,288]"]
    assert _tool("make_sequence").main(args) == 0
    seq = out / "sequence"
    truth = json.loads((seq / "truth.json").read_text())
    assert truth["fps"] == pytest.approx(30.0, rel=1e-3)
    assert len(truth["joints_world"]) == 4 and "l_knee" in truth["joints_world"][0]
    assert len(list((seq / "frames").glob("*.png"))) == 4
    for name in ("camera.yaml", "truth.json", "synth.json", "poses/pose6.png"):
        assert (out / "subject" / name).is_file(), name
    made = json.loads((seq / "synth.json").read_text())  # what made the sequence
    assert (made["start"], made["rest_frames_skipped"], made["step"]) == (300, 1, 4)
    assert made["seed"] == 5 and made["frames"] == 4
    # these frames stand on the floor: the lower ankle as high as in the body's own standing
    # posture (the feet flat, the soles on the floor), not lifted or pointed
    standing = json.loads((out / "subject" / "truth.json").read_text())["joints_world"]["pose1"]
    flat = min(standing["l_ankle"][2], standing["r_ankle"][2])
    for frame in truth["joints_world"]:
        assert abs(min(frame["l_ankle"][2], frame["r_ankle"][2]) - flat) < 0.02, frame
    # track it with the template's shape and the body's true segment lengths
    model_dir = tmp_path / "model"
    model_dir.mkdir()
    from torchfit.body.model import BodyModel

    segments = BodyModel("mpeg4_full").template.segments
    (model_dir / "params.json").write_text(
        json.dumps({"template": "mpeg4_full", "segment_scales": {s: [1, 1, 1] for s in segments}})
    )
    track_out = tmp_path / "track"
    code = _tool("track").main(
        [
            "--config",
            str(REPO / "configs/track.yaml"),
            "--model",
            str(model_dir),
            "--true-skeleton",
            str(out / "subject"),
            "--sequence",
            str(seq),
            "--out",
            str(track_out),
        ]
    )
    assert code in (0, 1)
    frames = json.loads((track_out / "joints_world.json").read_text())["frames"]
    assert len(frames) == 4
    rows = list(csv.DictReader((track_out / "track.csv").open()))
    assert [int(r["frame"]) for r in rows] == [0, 1, 2, 3]
    motion = read_bvh(track_out / "motion.bvh")
    assert motion.num_frames == 4
    assert bvhio.readAsBvh(str(track_out / "motion.bvh")).FrameCount == 4
    error = json.loads((track_out / "eval.json").read_text())["mean_joint_error_mm"]
    assert error < 200, error
