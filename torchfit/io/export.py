"""Export a fitted body: URDF + per-segment meshes, a single OBJ/GLB mesh, params.json.

The exported URDF is itself a template: ``load_template(<folder>/model.urdf)`` gives the fitted
body with unit scales.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchfit.errors import ShapeError
from torchfit.io.files import copy_atomic, make_dirs, write_atomic
from torchfit.io.meshes import save_mesh

__all__ = ["export_urdf", "export_mesh", "write_json"]


def export_urdf(model, scales: torch.Tensor, folder: str | Path) -> Path:
    """Write the scaled template as ``model.urdf`` + ``meshes/<segment>.obj`` (+ template.json).

    ``template.json`` is the template's own (scale groups, the segments whose origins are the
    measurement joints, landmark vertices), copied so that the folder loads back as a template
    with the same groups and measurements. Every file is written atomically
    (:func:`torchfit.io.files.write_atomic`), ``model.urdf`` after the meshes it names.

    Joint origins out of a segment are multiplied by that segment's scales and each mesh is
    scaled in its own frame, so the exported model at unit scale equals ``model`` at ``scales``.

    Args:
        model: a :class:`torchfit.body.model.BodyModel`.
        scales: (S, 3) per-segment scales of one subject.
        folder: output folder (created).

    Returns:
        Path of the written URDF.
    """
    t = model.template
    if tuple(scales.shape) != (t.num_segments, 3):
        raise ShapeError(f"scales: expected shape ({t.num_segments}, 3), got {tuple(scales.shape)}")
    sc = scales.detach().cpu().double().numpy()
    folder = Path(folder)
    make_dirs(folder / "meshes")
    root = ET.fromstring(t.urdf)
    for joint in root.iter("joint"):
        parent = joint.find("parent").get("link")
        origin = joint.find("origin")
        if parent in t.segments and origin is not None and origin.get("xyz"):
            xyz = np.array([float(v) for v in origin.get("xyz").split()])
            xyz = xyz * sc[t.segments.index(parent)]
            origin.set("xyz", " ".join(f"{v:.6f}" for v in xyz))
    verts = t.vertices.numpy()
    faces = t.faces.numpy()
    seg_of = t.vertex_segment.numpy()
    starts = np.searchsorted(seg_of, np.arange(t.num_segments))
    for link in root.iter("link"):
        name = link.get("name")
        mesh = link.find("visual/geometry/mesh")
        if mesh is None or name not in t.segments:
            continue
        s = t.segments.index(name)
        sel = seg_of == s
        f = faces[np.all(seg_of[faces] == s, axis=1)] - starts[s]
        save_mesh(folder / "meshes" / f"{name}.obj", verts[sel] * sc[s], f)
        mesh.set("filename", f"meshes/{name}.obj")
    ET.indent(root)
    path = folder / "model.urdf"
    meta = t.urdf_path.parent / "template.json"
    if meta.is_file():
        copy_atomic(meta, folder / "template.json")
    write_atomic(path, '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n")
    return path


def export_mesh(vertices: torch.Tensor, faces: torch.Tensor, path: str | Path) -> Path:
    """Write one posed body (V, 3) with faces (F, 3) as OBJ or GLB (by suffix)."""
    return save_mesh(path, vertices.detach().cpu().numpy(), faces.cpu().numpy())


def _plain(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


def write_json(path: str | Path, data: dict) -> Path:
    """Write ``data`` (tensors and arrays allowed) as indented JSON, atomically; returns the
    path.

    Raises:
        OutputError: the file cannot be written.
    """
    return write_atomic(path, json.dumps(_plain(data), indent=2) + "\n")
