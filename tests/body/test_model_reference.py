"""BodyModel against stored outputs, and ``nn.Module`` behaviour (``.to``, buffers).

``tests/data/body_model_reference.npz`` was written by ``tests/data/make_body_model_reference.py``
at commit 39faca2, when BodyModel was a plain class: the module version must give the same
numbers bit for bit in float64 (plain, forward-mode tangents, reverse-mode gradients) and
float32.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.autograd.forward_ad as fwad

from torchfit.body import BodyModel

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "body_model_reference.npz"
NAMES = ("scales", "joint_angles", "root_translation", "root_rotation")
TEMPLATES = ("mpeg4_full", "mpeg4_simple")


@cache
def reference() -> dict[str, np.ndarray]:
    with np.load(REFERENCE) as z:
        return dict(z)


@cache
def body(name: str) -> BodyModel:
    return BodyModel(name)


def ref(name: str, key: str) -> torch.Tensor:
    return torch.from_numpy(reference()[f"{name}/{key}"])


def same(actual: torch.Tensor, expected: torch.Tensor) -> None:
    """Bitwise equal (same dtype and shape, every element identical)."""
    assert actual.dtype == expected.dtype and actual.shape == expected.shape
    diff = (actual - expected).abs().max().item()
    assert torch.equal(actual, expected), f"max |difference| {diff:.3g}"


def inputs(name: str) -> dict[str, torch.Tensor]:
    return {k: ref(name, f"in/{k}") for k in NAMES}


@pytest.mark.parametrize("name", TEMPLATES)
def test_forward_matches_the_reference(name):
    model, p, vidx = body(name), inputs(name), ref(name, "vertex_index")
    same(model.joint_lower, ref(name, "joint_lower"))
    same(model.joint_upper, ref(name, "joint_upper"))
    out = model(**p)
    same(out.origins, ref(name, "origins"))
    same(out.rotations, ref(name, "rotations"))
    if name == "mpeg4_full":
        same(out.vertices, ref(name, "vertices"))
    else:
        same(out.vertices[:, vidx], ref(name, "vertices_sub"))
    same(model(**p, vertex_index=vidx).vertices, ref(name, "vertex_index_out"))
    mat = model(**{**p, "root_rotation": out.rotations[:, 0]}, vertex_index=vidx)
    same(mat.vertices, ref(name, "matrix_root_vertices"))


@pytest.mark.parametrize("name", TEMPLATES)
def test_forward_mode_tangents_match_the_reference(name):
    model, p, vidx = body(name), inputs(name), ref(name, "vertex_index")
    with fwad.dual_level():
        duals = {k: fwad.make_dual(v, ref(name, f"tangent/{k}")) for k, v in p.items()}
        out = model(**duals)
        verts = fwad.unpack_dual(out.vertices)
        same(fwad.unpack_dual(out.origins).tangent, ref(name, "dual_tangent_origins"))
        same(fwad.unpack_dual(out.rotations).tangent, ref(name, "dual_tangent_rotations"))
        same(verts.primal[:, vidx], ref(name, "dual_primal_vertices_sub"))
        if name == "mpeg4_full":
            same(verts.tangent, ref(name, "dual_tangent_vertices"))
        else:
            same(verts.tangent[:, vidx], ref(name, "dual_tangent_vertices_sub"))
        sub = fwad.unpack_dual(model(**duals, vertex_index=vidx).vertices).tangent
        same(sub, ref(name, "dual_tangent_vertex_index"))


@pytest.mark.parametrize("name", TEMPLATES)
def test_reverse_mode_gradients_match_the_reference(name):
    model = body(name)
    leaves = {k: v.clone().requires_grad_(True) for k, v in inputs(name).items()}
    loss = (model(**leaves).vertices * ref(name, "weights")).sum()
    for k, g in zip(leaves, torch.autograd.grad(loss, list(leaves.values())), strict=True):
        same(g, ref(name, f"grad/{k}"))


@pytest.mark.parametrize("name", TEMPLATES)
def test_float32_matches_the_reference(name):
    p32 = {k: v.float() for k, v in inputs(name).items()}
    vidx = ref(name, "vertex_index")
    built = BodyModel(name, dtype=torch.float32)
    moved = BodyModel(name).to(torch.float32)
    for model in (built, moved):
        assert model.dtype == torch.float32
        out = model(**p32, vertex_index=vidx)
        same(out.vertices, ref(name, "float32_vertex_index_out"))
        same(out.origins, ref(name, "float32_origins"))


def test_to_moves_every_tensor_and_the_properties_follow():
    model = BodyModel("mpeg4_simple")
    assert model.dtype == torch.float64 and model.device == torch.device("cpu")
    assert model.state_dict() == {}  # no parameters; the template defines the buffers
    buffers = dict(model.named_buffers())
    for key in ("_padded", "_vertices", "faces", "chain.axes", "chain.static_offsets",
                "chain.offsets", "chain.lower", "chain.upper"):  # fmt: skip
        assert key in buffers
    assert model.to(torch.float32) is model
    assert model.dtype == torch.float32
    floats = [b for b in model.buffers() if b.is_floating_point()]
    assert floats and all(b.dtype == torch.float32 for b in floats)
    assert model.faces.dtype == torch.int64  # index buffers keep their dtype
    assert model.joint_lower.dtype == model.offsets.dtype == torch.float32
    z = model.zeros(3)
    assert all(v.dtype == torch.float32 for v in z.values())
    out = model(**z)
    assert out.vertices.dtype == out.origins.dtype == out.rotations.dtype == torch.float32
    model.to("cpu", torch.float64)
    assert model.dtype == torch.float64
    assert model(**model.zeros(1)).vertices.dtype == torch.float64
    # a float64 -> float32 -> float64 round trip keeps what float32 holds
    fresh = BodyModel("mpeg4_simple")
    torch.testing.assert_close(
        model(**model.zeros(1)).vertices, fresh(**fresh.zeros(1)).vertices, rtol=0, atol=1e-6
    )


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_to_cuda_matches_the_cpu():
    name = "mpeg4_full"
    model = BodyModel(name).to("cuda")
    assert model.device.type == "cuda" and model.chain.frame_indices.device.type == "cuda"
    p = {k: v.cuda() for k, v in inputs(name).items()}
    out = model(**p)
    assert out.vertices.device.type == "cuda"
    torch.testing.assert_close(out.vertices.cpu(), ref(name, "vertices"), rtol=0, atol=1e-12)
    with fwad.dual_level():
        duals = {k: fwad.make_dual(v, ref(name, f"tangent/{k}").cuda()) for k, v in p.items()}
        tan = fwad.unpack_dual(model(**duals).vertices).tangent
    torch.testing.assert_close(tan.cpu(), ref(name, "dual_tangent_vertices"), rtol=0, atol=1e-12)
    cpu = BodyModel(name, device="cuda").to("cpu")
    same(cpu(**inputs(name)).vertices, ref(name, "vertices"))
