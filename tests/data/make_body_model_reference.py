"""Writes ``body_model_reference.npz``: BodyModel outputs that test_model_reference.py pins.

Run from the repository root: ``python tests/data/make_body_model_reference.py``. The stored
file was made at commit 39faca2 (BodyModel as a plain class on pytorch-kinematics' private
``_static_offsets`` / ``axes``), before BodyModel became an ``nn.Module``; re-running it on a
later version only reproduces that version's values.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.autograd.forward_ad as fwad

from torchfit.body import BodyModel

OUT = Path(__file__).resolve().parent / "body_model_reference.npz"
NAMES = ("scales", "joint_angles", "root_translation", "root_rotation")


def random_params(model, batch, gen):
    rand = lambda *s: torch.rand(*s, generator=gen, dtype=torch.float64)  # noqa: E731
    lo, hi = model.joint_lower, model.joint_upper
    return {
        "scales": 0.8 + 0.4 * rand(batch, model.num_segments, 3),
        "joint_angles": lo + (hi - lo) * (0.1 + 0.8 * rand(batch, model.num_dofs)),
        "root_translation": rand(batch, 3) - 0.5,
        "root_rotation": 2 * rand(batch, 3) - 1,
    }


def main() -> None:
    data: dict[str, np.ndarray] = {}
    gen = torch.Generator().manual_seed(20240611)
    for name in ("mpeg4_full", "mpeg4_simple"):
        model = BodyModel(name)
        p = random_params(model, 2, gen)
        tangents = {
            k: torch.randn(v.shape, generator=gen, dtype=torch.float64) for k, v in p.items()
        }
        vidx = torch.randperm(model.template.vertices.shape[0], generator=gen)[:40]
        w = torch.randn(2, model.template.vertices.shape[0], 3, generator=gen, dtype=torch.float64)
        for k, v in p.items():
            data[f"{name}/in/{k}"] = v.numpy()
            data[f"{name}/tangent/{k}"] = tangents[k].numpy()
        data[f"{name}/vertex_index"] = vidx.numpy()
        data[f"{name}/weights"] = w.numpy()
        data[f"{name}/joint_lower"] = model.joint_lower.numpy()
        data[f"{name}/joint_upper"] = model.joint_upper.numpy()

        out = model(**p)
        data[f"{name}/origins"] = out.origins.numpy()
        data[f"{name}/rotations"] = out.rotations.numpy()
        if name == "mpeg4_full":
            data[f"{name}/vertices"] = out.vertices.numpy()
        else:
            data[f"{name}/vertices_sub"] = out.vertices[:, vidx].numpy()
        data[f"{name}/vertex_index_out"] = model(**p, vertex_index=vidx).vertices.numpy()
        mat = model(**{**p, "root_rotation": out.rotations[:, 0]}, vertex_index=vidx)
        data[f"{name}/matrix_root_vertices"] = mat.vertices.numpy()

        # forward mode: every input dual at once
        with fwad.dual_level():
            duals = {k: fwad.make_dual(v, tangents[k]) for k, v in p.items()}
            dout = model(**duals)
            tv = fwad.unpack_dual(dout.vertices).tangent
            data[f"{name}/dual_primal_vertices_sub"] = (
                fwad.unpack_dual(dout.vertices).primal[:, vidx].numpy()
            )
            data[f"{name}/dual_tangent_origins"] = fwad.unpack_dual(dout.origins).tangent.numpy()
            data[f"{name}/dual_tangent_rotations"] = fwad.unpack_dual(
                dout.rotations
            ).tangent.numpy()
            if name == "mpeg4_full":
                data[f"{name}/dual_tangent_vertices"] = tv.numpy()
            else:
                data[f"{name}/dual_tangent_vertices_sub"] = tv[:, vidx].numpy()
            dsub = model(**duals, vertex_index=vidx).vertices
            data[f"{name}/dual_tangent_vertex_index"] = fwad.unpack_dual(dsub).tangent.numpy()

        # reverse mode
        leaves = {k: v.clone().requires_grad_(True) for k, v in p.items()}
        grads = torch.autograd.grad((model(**leaves).vertices * w).sum(), list(leaves.values()))
        for k, g in zip(leaves, grads, strict=True):
            data[f"{name}/grad/{k}"] = g.numpy()

        # float32
        m32 = BodyModel(name, dtype=torch.float32)
        o32 = m32(**{k: v.float() for k, v in p.items()}, vertex_index=vidx)
        data[f"{name}/float32_vertex_index_out"] = o32.vertices.numpy()
        data[f"{name}/float32_origins"] = o32.origins.numpy()
    np.savez_compressed(OUT, **data)
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes, {len(data)} arrays)")


if __name__ == "__main__":
    main()
