"""Measurements of a model against direct mesh geometry; exports that reload identically."""

import json
import math

import pytest
import torch

from torchfit.body.measure import measure_model
from torchfit.body.model import BodyModel
from torchfit.io.export import export_mesh, export_urdf, write_json
from torchfit.measurements import MEASUREMENT_KEYS


def test_template_measurements_match_the_mesh(model):
    ones = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    m = measure_model(model, ones)
    assert list(m) == list(MEASUREMENT_KEYS)
    v = model(**model.zeros(1)).vertices[0]
    # height: floor (lowest vertex: a sole) to the highest vertex (top of the head)
    assert float(m["height_m"][0]) == pytest.approx(float(v[:, 2].max() - v[:, 2].min()), abs=1e-9)
    # arm span: the T-pose's extent across the body, fingertip to fingertip
    p = model.zeros(1)
    for s in "lr":
        p["joint_angles"][0, model.dof_index(f"{s}_shoulder_abduct")] = math.radians(90)
    vt = model(**p).vertices[0]
    assert float(m["arm_span_m"][0]) == pytest.approx(
        float(vt[:, 1].max() - vt[:, 1].min()), abs=0.01
    )
    # a plausible adult: proportions as anthropometry has them
    h = float(m["height_m"][0])
    assert 1.5 < h < 1.9
    assert 0.95 < float(m["arm_span_m"][0]) / h < 1.06
    assert 0.24 < float(m["lower_leg_m"][0]) / h < 0.32


def test_measurements_follow_the_scales(model):
    s = torch.ones(2, model.num_segments, 3, dtype=torch.float64)
    s[1] = 1.1
    idx = model.template.segment_index
    m = measure_model(model, s)
    for key in MEASUREMENT_KEYS:
        torch.testing.assert_close(m[key][1], 1.1 * m[key][0])
    # lengthening the forearm changes forearm and arm span, not the upper arm
    s2 = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    s2[0, idx("l_forearm"), 2] = s2[0, idx("r_forearm"), 2] = 1.2
    m2 = measure_model(model, s2)
    torch.testing.assert_close(m2["forearm_m"], 1.2 * m["forearm_m"][:1])
    torch.testing.assert_close(m2["upper_arm_m"], m["upper_arm_m"][:1])
    delta = float(m2["arm_span_m"][0] - m["arm_span_m"][0])
    assert delta == pytest.approx(2 * 0.2 * float(m["forearm_m"][0]), rel=1e-6)


def test_measurements_are_differentiable(model):
    s = torch.ones(1, model.num_segments, 3, dtype=torch.float64, requires_grad=True)
    (grad,) = torch.autograd.grad(measure_model(model, s)["height_m"].sum(), s)
    idx = model.template.segment_index
    assert grad[0, idx("l_calf"), 2] > 0  # longer shanks make a taller body
    assert grad[0, idx("l_forearm")].abs().max() == 0


def test_exported_urdf_reloads_as_the_scaled_body(model, tmp_path):
    g = torch.Generator().manual_seed(0)
    scales = 0.8 + 0.4 * torch.rand(1, model.num_segments, 3, generator=g, dtype=torch.float64)
    path = export_urdf(model, scales[0], tmp_path / "fitted")
    again = BodyModel(str(path))
    assert again.dof_names == model.dof_names
    assert again.template.scale_groups == model.template.scale_groups
    p = model.zeros(1)
    p["joint_angles"] = 0.3 * torch.rand(1, model.num_dofs, generator=g, dtype=torch.float64)
    expected = model(scales, p["joint_angles"], p["root_translation"], p["root_rotation"])
    got = again(
        torch.ones_like(scales), p["joint_angles"], p["root_translation"], p["root_rotation"]
    )
    torch.testing.assert_close(got.vertices, expected.vertices, atol=1e-5, rtol=0)
    ones = torch.ones_like(scales)
    torch.testing.assert_close(
        measure_model(again, ones)["height_m"],
        measure_model(model, scales)["height_m"],
        atol=1e-5,
        rtol=0,
    )


def test_mesh_and_json_exports(model, tmp_path):
    import trimesh

    out = model(**model.zeros(1))
    for suffix in (".obj", ".glb"):
        path = export_mesh(out.vertices[0], model.faces, tmp_path / f"body{suffix}")
        mesh = trimesh.load(path, force="mesh", process=False)
        assert len(mesh.faces) == model.faces.shape[0]
    path = write_json(tmp_path / "params.json", {"scales": torch.ones(2, 3), "n": 3})
    assert json.loads(path.read_text()) == {"scales": [[1.0] * 3] * 2, "n": 3}
