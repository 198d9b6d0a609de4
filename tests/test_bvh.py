"""BVH: the reader against the CMU file, the writer read back by an independent parser
(bvhio), and the body model's skeleton and motion written as BVH."""

import os
from pathlib import Path

import numpy as np
import pytest
import torch

from torchfit.body.bvh import Y_UP, model_motion
from torchfit.body.model import BodyModel
from torchfit.errors import DataError
from torchfit.io.bvh import euler_to_matrix, read_bvh, write_bvh

bvhio = pytest.importorskip("bvhio")
glm = pytest.importorskip("glm")

REPO = Path(__file__).resolve().parents[1]
CMU = Path(os.environ.get("TORCHFIT_SHARED", REPO / ".." / "shared")) / "data" / "cmu-mocap-sample"


def _bvhio_world(path: Path, frame: int) -> dict[str, np.ndarray]:
    root = bvhio.readAsHierarchy(str(path))
    root.loadPose(frame)
    return {j.Name: np.array(list(j.PositionWorld)) for j, _, _ in root.layout()}


@pytest.fixture(scope="module")
def model():
    return BodyModel("mpeg4_full")


def test_model_motion_reads_back_with_bvhio(model, tmp_path):
    g = torch.Generator().manual_seed(0)
    f = 4
    scales = 0.9 + 0.2 * torch.rand(model.num_segments, 3, generator=g, dtype=torch.float64)
    lo, hi = model.joint_lower, model.joint_upper
    angles = lo + (hi - lo) * (
        0.3 + 0.4 * torch.rand(f, model.num_dofs, generator=g, dtype=torch.float64)
    )
    trans = torch.randn(f, 3, generator=g, dtype=torch.float64)
    rot = 0.5 * torch.randn(f, 3, generator=g, dtype=torch.float64)
    motion = model_motion(model, scales, angles, trans, rot, frame_time=0.04)
    path = write_bvh(tmp_path / "m.bvh", motion)
    # our own reader gives back the same offsets, channels and values
    back = read_bvh(path)
    assert back.names == motion.names and back.channels == motion.channels
    np.testing.assert_allclose(back.offsets, motion.offsets, atol=1e-6)
    np.testing.assert_allclose(back.frames, motion.frames, atol=1e-5)
    assert back.frame_time == pytest.approx(0.04)
    # bvhio: the same offsets, and its world positions are the model's joint centres
    out = model(scales[None].expand(f, -1, -1), angles, trans, rot)
    container = bvhio.readAsBvh(str(path))
    assert container.FrameCount == f and container.FrameTime == pytest.approx(0.04)
    slices = motion.channel_slices()
    for joint, _, _ in container.Root.layout():
        k = motion.names.index(joint.Name)
        assert list(joint.Channels) == motion.channels[k]
        np.testing.assert_allclose(list(joint.Offset), motion.offsets[k], atol=1e-5)
        values = motion.frames[:, slices[k]][:, -3:]
        for i in range(f):
            theirs = np.array(glm.mat3_cast(joint.Keyframes[i].Rotation).to_list()).T
            ours = euler_to_matrix(np.radians(values[i]), "ZXY")
            np.testing.assert_allclose(theirs, ours, atol=1e-5, err_msg=f"{joint.Name} frame {i}")
    for i in range(f):
        world = _bvhio_world(path, i)
        for s, name in enumerate(model.template.segments):
            want = Y_UP @ out.origins[i, s].numpy()
            np.testing.assert_allclose(world[name], want, atol=2e-4, err_msg=f"{name} frame {i}")


def test_neutral_skeleton_has_the_subject_segment_lengths(model):
    scales = torch.ones(model.num_segments, 3, dtype=torch.float64)
    scales[model.template.segment_index("l_thigh")] *= 1.2
    motion = model_motion(model, scales)
    calf = motion.names.index("l_calf")
    want = 1.2 * np.linalg.norm(model.offsets[model.template.segment_index("l_calf")].numpy())
    assert np.linalg.norm(motion.offsets[calf]) == pytest.approx(want, rel=1e-6)
    assert motion.num_frames == 1 and np.allclose(motion.frames, 0, atol=1e-9)


@pytest.mark.skipif(not (CMU / "01_01.bvh").is_file(), reason="shared CMU data not present")
def test_cmu_file_matches_bvhio_and_round_trips(tmp_path):
    motion = read_bvh(CMU / "01_01.bvh")
    assert motion.num_frames == 2752 and motion.names[0] == "Hips"
    assert motion.frame_time == pytest.approx(1 / 120, rel=1e-3)
    motion.frames = motion.frames[:50]
    path = write_bvh(tmp_path / "cmu.bvh", motion)
    ours, _ = motion.world(37)
    theirs = _bvhio_world(path, 37)
    for k, name in enumerate(motion.names):
        np.testing.assert_allclose(theirs[name], ours[k], atol=1e-3)


def test_bad_bvh_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.bvh"
    bad.write_text(
        "HIERARCHY\nROOT Hips\n{\nOFFSET 0 0 0\nCHANNELS 1 Wobble\n}\nMOTION\n"
        "Frames: 1\nFrame Time: 0.1\n0\n"
    )
    with pytest.raises(DataError, match="unknown channel 'Wobble'"):
        read_bvh(bad)
    with pytest.raises(DataError, match="not found"):
        read_bvh(tmp_path / "missing.bvh")


def test_fit_outputs_hold_the_neutral_skeleton_as_bvh(model, tmp_path):
    from torchfit.pipeline.outputs import write_model

    scales = torch.full((model.num_segments, 3), 1.1, dtype=torch.float64)
    write_model(model, scales, tmp_path, "obj")
    assert (tmp_path / "model.urdf").is_file()
    container = bvhio.readAsBvh(str(tmp_path / "model.bvh"))
    assert container.FrameCount == 1 and container.Root.Name == model.template.segments[0]
    joints = {j.Name: np.array(list(j.Offset)) for j, _, _ in container.Root.layout()}
    assert set(joints) == set(model.template.segments)
    k = model.template.segment_index("l_calf")
    np.testing.assert_allclose(
        np.linalg.norm(joints["l_calf"]),
        1.1 * np.linalg.norm(model.offsets[k].numpy()),
        rtol=1e-5,
    )
