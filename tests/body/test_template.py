"""Template loading: shipped templates, user URDFs, error paths."""

from pathlib import Path

import pytest
import torch

from torchfit.body.kinematics import SkeletonChain
from torchfit.body.template import available_templates, load_template
from torchfit.errors import ModelError

MPEG4_DOFS = [
    "l_shoulder_flexion",
    "l_shoulder_abduct",
    "l_shoulder_twisting",
    "l_elbow_flexion",
    "l_hip_flexion",
    "l_hip_abduct",
    "l_knee_flexion",
    "r_shoulder_abduct",
    "r_knee_flexion",
    "vc4_tilt",
    "skullbase_torsion",
]


def test_shipped_templates():
    assert available_templates() == ["mpeg4_full", "mpeg4_simple"]
    full, simple = load_template("mpeg4_full"), load_template("mpeg4_simple")
    # light meshes: a few thousand triangles in all
    assert 1000 < full.faces.shape[0] < 6000
    assert 1000 < simple.faces.shape[0] < 6000
    assert full.num_segments == 20 and simple.num_segments == 15
    assert full.parents[0] == -1 and (full.parents[1:] >= 0).all()
    # parents come before children
    assert all(p < i for i, p in enumerate(full.parents) if p >= 0)
    # the full model has articulated vertebra groups, the simple one a rigid torso
    full_dofs = SkeletonChain(full.urdf, full.segments, full.parents).dof_names
    simple_dofs = SkeletonChain(simple.urdf, simple.segments, simple.parents).dof_names
    for dof in MPEG4_DOFS:
        assert dof in full_dofs and dof in simple_dofs
    assert {"vl5_tilt", "vt10_roll", "vt1_torsion", "l_sternoclavicular_abduct"} <= set(full_dofs)
    assert not any(d.startswith(("vl5", "vt10", "vt1_")) for d in simple_dofs)
    # left/right symmetry in the scale groups
    g = full.segment_group
    seg = full.segments.index
    assert g[seg("l_thigh")] == g[seg("r_thigh")] != g[seg("l_calf")]
    assert g[seg("l5")] == g[seg("t10")]  # spine coupling
    assert len(full.scale_groups) == 12


def test_joint_limits_come_from_the_urdf():
    t = load_template("mpeg4_full")
    chain = SkeletonChain(t.urdf, t.segments, t.parents)
    k = chain.dof_names.index("l_knee_flexion")
    assert chain.lower[k] == pytest.approx(0.0)
    assert chain.upper[k] == pytest.approx(torch.pi * 150 / 180, abs=1e-5)
    assert (chain.lower < chain.upper).all()


def test_meshes_are_in_segment_frames():
    t = load_template("mpeg4_full")
    # the thigh hangs below the hip joint (its origin): all z <= a few cm
    thigh = t.vertices[t.vertex_segment == t.segments.index("l_thigh")]
    assert thigh[:, 2].max() < 0.12 and thigh[:, 2].min() > -0.5


TINY_URDF = """<?xml version="1.0"?>
<robot name="tiny">
  <link name="base"><visual><geometry><mesh filename="box.obj"/></geometry></visual></link>
  <joint name="l_arm_abduct" type="revolute">
    <parent link="base"/><child link="l_arm"/>
    <origin xyz="0 0.2 0" rpy="0 0 0"/><axis xyz="1 0 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <link name="l_arm"><visual><geometry><mesh filename="box.obj"/></geometry></visual></link>
  <joint name="r_arm_abduct" type="revolute">
    <parent link="base"/><child link="r_arm"/>
    <origin xyz="0 -0.2 0" rpy="0 0 0"/><axis xyz="-1 0 0"/>
    <limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
  <link name="r_arm"><visual><geometry><mesh filename="box.obj"/></geometry></visual></link>
</robot>
"""

BOX_OBJ = "\n".join(
    ["v 0 0 0", "v 0.1 0 0", "v 0 0.1 0", "v 0 0 -0.1", "f 1 2 3", "f 1 2 4", "f 1 3 4", "f 2 3 4"]
)


def write_tiny(folder: Path, urdf: str = TINY_URDF) -> Path:
    (folder / "box.obj").write_text(BOX_OBJ + "\n")
    path = folder / "tiny.urdf"
    path.write_text(urdf)
    return path


def test_user_urdf_without_sidecar(tmp_path):
    t = load_template(write_tiny(tmp_path))
    assert t.segments == ["base", "l_arm", "r_arm"]
    assert t.scale_groups == ["base", "arm"]  # l_/r_ pairs share one group by default
    assert t.vertices.shape == (12, 3)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda u: u.replace("<robot", "<robot<"), "malformed URDF"),
        (lambda u: u.replace("box.obj", "nothere.obj", 1), "mesh file not found"),
        (
            lambda u: u.replace(
                '<link name="base"><visual><geometry><mesh filename="box.obj"/>'
                "</geometry></visual></link>",
                '<link name="base"/>',
            ),
            "one root link carrying a mesh",
        ),
    ],
)
def test_bad_urdf(tmp_path, mutate, message):
    with pytest.raises(ModelError, match=message):
        load_template(write_tiny(tmp_path, mutate(TINY_URDF)))


def test_unknown_template_names_the_choices():
    with pytest.raises(ModelError, match=r"unknown template 'mpeg5'.*mpeg4_full"):
        load_template("mpeg5")
    with pytest.raises(ModelError, match="template URDF not found"):
        load_template("/nonexistent/model.urdf")
