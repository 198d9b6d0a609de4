"""ParamLayout / ResidualLayout: the one place that says where parameters and residuals live.

References: the parameter order written out by hand for a two-posture toy template, and the
residual widths of a real problem (the residual function's own output)."""

import pytest
import torch

from torchfit.errors import ConfigError
from torchfit.fit.layout import ROOT_NAMES, JointBounds, ParamLayout


def toy(free=None) -> ParamLayout:
    dofs = ["a", "b", "c"]
    nominal = {1: torch.tensor([0.1, 0.2, 0.3]), 3: torch.tensor([1.0, 2.0, 3.0])}
    return ParamLayout(
        ["thigh", "calf", "chest"],
        dofs,
        torch.tensor([-1.0, -2.0, -3.0]),
        torch.tensor([1.0, 2.0, 3.0]),
        nominal,
        free or {1: ["b"], 3: ["c", "a"]},
        (0.5, 1.5),
        JointBounds(translation_max_m=0.1, yaw_max_deg=90.0, tilt_max_deg=180.0),
    )


def test_names_bounds_and_start_in_the_documented_order():
    lay = toy()
    scales = [f"scale:{g}:{a}" for g in ("thigh", "calf", "chest") for a in "xyz"]
    pose1 = ["pose1:b"] + [f"pose1:{r}" for r in ROOT_NAMES]
    pose3 = ["pose3:c", "pose3:a"] + [f"pose3:{r}" for r in ROOT_NAMES]
    assert lay.names == tuple(scales + pose1 + pose3)
    assert lay.num_params == 9 + 6 + 7 and lay.num_scale_params == 9
    lo, hi, x0 = lay.lower(), lay.upper(), lay.initial()
    assert lo[:9].tolist() == [0.5] * 9 and hi[:9].tolist() == [1.5] * 9
    b1 = lay.blocks[1]
    assert (b1.joints, b1.root) == (slice(9, 10), slice(10, 15))
    assert lo[b1.joints].tolist() == [-2.0] and x0[b1.joints].tolist() == [pytest.approx(0.2)]
    expected = torch.tensor([-0.1, -0.1, -torch.pi / 2, -torch.pi, -torch.pi])
    torch.testing.assert_close(lo[b1.root], expected)
    b3 = lay.blocks[3]
    assert b3.dofs == (2, 0) and b3.columns == slice(15, 22)
    assert x0[b3.joints].tolist() == [3.0, 1.0]
    assert b3.root_column("ty") == lay.names.index("pose3:ty") == 18
    assert lay.scale_column("calf", "z") == 5 and lay.scale_column("tail", "z") is None


def test_scale_aliases_stage_columns_and_reading_rows():
    lay = toy()
    assert lay.scale_indices(["legs"]) == [2, 5]  # thigh:z, calf:z
    assert lay.scale_indices(["chest:xy", "thigh"]) == [0, 1, 2, 6, 7]
    assert lay.free_indices(["legs"], joints=True, root=False) == [2, 5, 9, 15, 16]
    assert len(lay.free_indices(["all"], joints=False, root=True)) == 9 + 10
    with pytest.raises(ConfigError, match="unknown scale group 'tail'"):
        lay.scale_indices(["tail"])
    with pytest.raises(ConfigError, match="bad axis 'w'"):
        lay.scale_indices(["chest:w"])
    x = torch.arange(lay.num_params, dtype=torch.float64)[None]
    assert lay.group_scales(x).shape == (1, 3, 3) and float(lay.group_scales(x)[0, 1, 2]) == 5
    assert lay.root_offsets(x[0], 1) == dict(zip(ROOT_NAMES, [10.0, 11, 12, 13, 14], strict=True))
    assert lay.free_joint_names(3) == ["c", "a"]


def test_unknown_free_joint_is_named():
    with pytest.raises(ConfigError, match=r"free_joints.pose1: unknown joint DOFs \['z'\]"):
        toy({1: ["z"]})


def test_residual_layout_splits_a_row():
    rl = toy().residual_layout([4, 2])
    assert (rl.e_p(1), rl.e_m(1)) == (slice(0, 4), 4)
    assert (rl.e_p(3), rl.e_m(3)) == (slice(5, 7), 7)
    assert rl.barrier == slice(8, 30) and rl.size == 30
    r = torch.zeros(30)
    r[0:4] = 0.5  # RMS 1 px: e_P entries are d / sqrt(C)
    r[4], r[7] = 3.0, 7.0
    assert rl.per_pose_quality(r) == {1: (1.0, 3.0), 3: (0.0, 7.0)}
