"""Template body models: a URDF skeleton with one rigid mesh per segment.

A *segment* is a URDF link that carries a visual mesh; links without a mesh are the
intermediate frames of multi-DOF joints (``l_shoulder_flexion`` → ``l_shoulder_abduct`` →
``l_shoulder_twisting``). Every translation between two segments must sit at the first joint
out of the parent segment (later joints of the group rotate in place), so that the offset of a
child segment is a constant vector in its parent segment's frame — which is what a segment
scale σ multiplies.

An optional ``template.json`` beside the URDF adds scale groups (segments sharing one scale
triple: left/right symmetry, spine coupling), the segments whose origins are the measurement
joints (``l_shoulder`` → ``l_upperarm``) and landmark vertices (``head_top``, fingertips,
soles). Without it, groups default to one per segment with ``l_``/``r_`` pairs merged.

Frames: metres; the shipped templates use x forward, y left, z up, neutral pose standing on
z = 0 with the arms hanging.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from torchfit.errors import ModelError
from torchfit.io.meshes import load_mesh_arrays

__all__ = ["Template", "load_template", "TEMPLATE_DIR", "available_templates"]

TEMPLATE_DIR = Path(__file__).resolve().parent / "templates"


def available_templates() -> list[str]:
    """Names of the templates shipped with torchfit."""
    return sorted(p.parent.name for p in TEMPLATE_DIR.glob("*/model.urdf"))


@dataclass
class Template:
    """A loaded template (numpy/torch data on the CPU, float64).

    Attributes:
        name: template name.
        urdf_path: the URDF file.
        urdf: URDF text (what pytorch-kinematics loads).
        segments: S segment (link) names, parents before children.
        parents: (S,) parent segment index, -1 for the root.
        vertices: (V, 3) mesh vertices in their segment's frame, grouped by segment.
        vertex_segment: (V,) segment index of each vertex.
        faces: (F, 3) indices into ``vertices``.
        scale_groups: G group names.
        segment_group: (S,) group index of each segment.
        joints: measurement joint name -> segment index whose origin is that joint.
        landmarks: landmark name -> vertex index.
    """

    name: str
    urdf_path: Path
    urdf: str
    segments: list[str]
    parents: np.ndarray
    vertices: torch.Tensor
    vertex_segment: torch.Tensor
    faces: torch.Tensor
    scale_groups: list[str]
    segment_group: torch.Tensor
    joints: dict[str, int]
    landmarks: dict[str, int]

    @property
    def num_segments(self) -> int:
        """S, the number of segments."""
        return len(self.segments)

    def segment_index(self, name: str) -> int:
        """Index of segment ``name``; raises ModelError naming the valid ones."""
        try:
            return self.segments.index(name)
        except ValueError:
            raise ModelError(
                f"template {self.name!r} has no segment {name!r} (segments: {self.segments})"
            ) from None


def _default_groups(segments: list[str]) -> dict[str, str]:
    groups = {}
    for s in segments:
        groups[s] = (
            s[2:]
            if s[:2] in ("l_", "r_") and ("l_" + s[2:]) in segments and ("r_" + s[2:]) in segments
            else s
        )
    return groups


def load_template(name_or_path: str | Path) -> Template:
    """Load a shipped template by name (``"mpeg4_full"``, ``"mpeg4_simple"``) or a URDF path.

    Raises:
        ModelError: unknown name, missing or malformed URDF / meshes / template.json.
    """
    path = Path(name_or_path)
    if path.suffix.lower() != ".urdf":
        shipped = TEMPLATE_DIR / str(name_or_path) / "model.urdf"
        if not shipped.is_file():
            raise ModelError(
                f"unknown template {str(name_or_path)!r}: expected one of "
                f"{available_templates()} or a path to a .urdf file"
            )
        path = shipped
    if not path.is_file():
        raise ModelError(f"template URDF not found: {path}")
    text = path.read_text()
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ModelError(f"{path}: malformed URDF: {exc}") from exc

    meshes: dict[str, Path] = {}
    for link in root.iter("link"):
        mesh = link.find("visual/geometry/mesh")
        if mesh is not None:
            meshes[link.get("name")] = path.parent / mesh.get("filename", "")
    parent_of: dict[str, str] = {}
    for joint in root.iter("joint"):
        parent, child = joint.find("parent"), joint.find("child")
        if parent is None or child is None:
            raise ModelError(f"{path}: joint {joint.get('name')!r} lacks a parent or child")
        parent_of[child.get("link")] = parent.get("link")
    roots = [n for n in (link.get("name") for link in root.iter("link")) if n not in parent_of]
    if len(roots) != 1 or roots[0] not in meshes:
        raise ModelError(f"{path}: expected one root link carrying a mesh, found roots {roots}")

    def parent_segment(link: str) -> str | None:
        cur = parent_of.get(link)
        while cur is not None and cur not in meshes:
            cur = parent_of.get(cur)
        return cur

    def depth(link: str) -> int:
        d = 0
        while link in parent_of:
            link, d = parent_of[link], d + 1
        return d

    segments = sorted(meshes, key=depth)
    parents = np.array([segments.index(p) if (p := parent_segment(s)) else -1 for s in segments])

    verts, faces, vseg = [], [], []
    offset = 0
    for i, seg in enumerate(segments):
        v, f = load_mesh_arrays(meshes[seg])
        verts.append(v)
        faces.append(f + offset)
        vseg.append(np.full(len(v), i))
        offset += len(v)

    meta_path = path.parent / "template.json"
    meta = {}
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
        except json.JSONDecodeError as exc:
            raise ModelError(f"{meta_path}: invalid JSON: {exc}") from exc
    groups_map = meta.get("scale_groups") or _default_groups(segments)
    missing = [s for s in segments if s not in groups_map]
    if missing:
        raise ModelError(f"{meta_path}: scale_groups lacks segments {missing}")
    scale_groups = list(dict.fromkeys(groups_map[s] for s in segments))
    joints = {}
    for jname, seg in meta.get("joints", {}).items():
        if seg not in segments:
            raise ModelError(f"{meta_path}: joint {jname!r} names unknown segment {seg!r}")
        joints[jname] = segments.index(seg)
    starts = np.cumsum([0] + [len(v) for v in verts])
    landmarks = {}
    for lname, (seg, idx) in meta.get("landmarks", {}).items():
        if seg not in segments:
            raise ModelError(f"{meta_path}: landmark {lname!r} names unknown segment {seg!r}")
        k = segments.index(seg)
        if not 0 <= idx < len(verts[k]):
            raise ModelError(f"{meta_path}: landmark {lname!r} vertex {idx} out of range")
        landmarks[lname] = int(starts[k] + idx)

    return Template(
        name=meta.get("name", path.parent.name),
        urdf_path=path,
        urdf=text,
        segments=segments,
        parents=parents,
        vertices=torch.from_numpy(np.concatenate(verts)),
        vertex_segment=torch.from_numpy(np.concatenate(vseg)),
        faces=torch.from_numpy(np.concatenate(faces)),
        scale_groups=scale_groups,
        segment_group=torch.tensor([scale_groups.index(groups_map[s]) for s in segments]),
        joints=joints,
        landmarks=landmarks,
    )
