"""benchmarks/track_floor.py: the floor pose it fits to given joints (no sequence, no
tracking): the template's own joints at a known pose are matched to a millimetre, and a pose's
error against its own joints is zero."""

import numpy as np
import pytest
import torch
from scripts import load_script

from torchfit.body.model import BodyModel


@pytest.fixture(scope="module")
def tool():
    return load_script("benchmarks/track_floor.py")


def test_floor_pose_matches_the_joints_of_a_known_pose(tool):
    model = BodyModel("mpeg4_full")
    sc = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    truth = np.zeros(6 + model.num_dofs)
    truth[:3] = (0.1, -0.2, 0.95)
    truth[5] = 0.4  # turned about the vertical
    for name, angle in (
        ("l_shoulder_abduct", 0.6),
        ("r_elbow_flexion", 0.8),
        ("l_knee_flexion", 0.5),
    ):
        truth[6 + model.dof_index(name)] = angle
    target = np.stack(
        np.split(tool.joint_residual(model, sc, truth, 0.0)[: 3 * len(tool.NAMES)], len(tool.NAMES))
    )
    assert np.allclose(tool.joint_error_mm(model, sc, truth, target), 0.0)
    start = np.zeros_like(truth)
    start[:3] = target.mean(0)
    fitted = tool.floor_pose(model, sc, target, start)
    err = tool.joint_error_mm(model, sc, fitted, target)
    assert err.shape == (len(tool.NAMES),) and err.max() < 1.0, err
    # the joint angles stay within the template's limits
    q = fitted[6:]
    assert (q >= model.joint_lower.numpy() - 1e-9).all() and (
        q <= model.joint_upper.numpy() + 1e-9
    ).all()
