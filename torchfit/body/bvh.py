"""A body model's skeleton and motion as a BVH :class:`torchfit.io.bvh.Motion`.

Every segment is a BVH joint at its origin (the proximal joint centre), with the subject's
own segment lengths (template offsets times the parent segment's scales), metres. BVH is
y up: the model's world (z up) is written through the fixed rotation
``(x, y, z) -> (x, z, -y)``, so the model's up axis is BVH's +y and its backward axis (+y)
is BVH's -z. The root has six channels ``Xposition Yposition Zposition Zrotation Xrotation
Yrotation``, every other joint the three rotations; each leaf segment ends in an end site at
its vertex farthest from its origin in the neutral pose.
"""

from __future__ import annotations

import numpy as np
import torch

from torchfit.errors import check_shape
from torchfit.io.bvh import Motion, matrix_to_euler

__all__ = ["Y_UP", "model_motion", "depth_first"]

#: model world (z up) -> BVH frame (y up).
Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

_ORDER = "ZXY"
_ROT_CHANNELS = [f"{a}rotation" for a in _ORDER]


def depth_first(parents: list[int]) -> list[int]:
    """Segment indices in depth-first order (each subtree contiguous), children in index
    order."""
    children: dict[int, list[int]] = {i: [] for i in range(len(parents))}
    for i, p in enumerate(parents):
        if p >= 0:
            children[int(p)].append(i)
    out: list[int] = []
    stack = [i for i, p in enumerate(parents) if p < 0][::-1]
    while stack:
        i = stack.pop()
        out.append(i)
        stack.extend(children[i][::-1])
    return out


def model_motion(
    model,
    scales: torch.Tensor,
    joint_angles: torch.Tensor | None = None,
    root_translation: torch.Tensor | None = None,
    root_rotation: torch.Tensor | None = None,
    frame_time: float = 1 / 30,
) -> Motion:
    """The posed body as BVH: one frame per row of the pose parameters.

    Args:
        model: a :class:`torchfit.body.model.BodyModel`.
        scales: (S, 3) the subject's segment scales.
        joint_angles: (F, Q) radians; None: one neutral frame.
        root_translation: (F, 3) metres (zeros when None).
        root_rotation: (F, 3) axis-angle (zeros when None).
        frame_time: seconds per frame.

    Returns:
        A :class:`Motion` (metres, degrees, y up).
    """
    t = model.template
    check_shape("scales", scales, (t.num_segments, 3))
    kw = {"dtype": model.dtype, "device": model.device}
    if joint_angles is None:
        joint_angles = torch.zeros(1, model.num_dofs, **kw)
    f = joint_angles.shape[0]
    check_shape("joint_angles", joint_angles, (f, model.num_dofs))
    if root_translation is None:
        root_translation = torch.zeros(f, 3, **kw)
    if root_rotation is None:
        root_rotation = torch.zeros(f, 3, **kw)
    sc = scales.to(**kw)
    with torch.no_grad():
        out = model(
            sc.expand(f, -1, -1),
            joint_angles.to(**kw),
            root_translation.to(**kw),
            root_rotation.to(**kw),
        )
        neutral = model(sc[None], **{k: v for k, v in model.zeros(1).items() if k != "scales"})
    parents = [int(p) for p in t.parents]
    order = depth_first(parents)
    new_index = {s: k for k, s in enumerate(order)}
    offsets_model = (sc[torch.tensor([max(p, 0) for p in parents])] * model.offsets).cpu()
    offsets_model = offsets_model.double().numpy()
    rot = out.rotations.detach().cpu().double().numpy()  # (F, S, 3, 3)
    origin = out.origins.detach().cpu().double().numpy()  # (F, S, 3)
    names, new_parents, offsets, channels = [], [], [], []
    for s in order:
        p = parents[s]
        names.append(t.segments[s])
        new_parents.append(-1 if p < 0 else new_index[p])
        offsets.append(np.zeros(3) if p < 0 else Y_UP @ offsets_model[s])
        channels.append(([f"{a}position" for a in "XYZ"] if p < 0 else []) + _ROT_CHANNELS)
    # leaf end sites: the farthest neutral-pose vertex of the segment, in its frame
    verts = neutral.vertices[0].detach().cpu().double().numpy()
    n_origin = neutral.origins[0].detach().cpu().double().numpy()
    seg_of = t.vertex_segment.numpy()
    end_sites = {}
    for k, s in enumerate(order):
        if s in parents:
            continue
        local = verts[seg_of == s] - n_origin[s]
        end = local[np.argmax(np.linalg.norm(local, axis=1))] if len(local) else np.zeros(3)
        end_sites[k] = Y_UP @ end
    frames = np.zeros((f, sum(len(c) for c in channels)))
    col = 0
    for s in order:
        p = parents[s]
        local = rot[:, s] if p < 0 else np.swapaxes(rot[:, p], -1, -2) @ rot[:, s]
        local = Y_UP @ local @ Y_UP.T
        if p < 0:
            frames[:, col : col + 3] = origin[:, s] @ Y_UP.T
            col += 3
        frames[:, col : col + 3] = np.degrees(matrix_to_euler(local, _ORDER))
        col += 3
    return Motion(
        names=names,
        parents=new_parents,
        offsets=np.array(offsets),
        channels=channels,
        end_sites=end_sites,
        frame_time=float(frame_time),
        frames=frames,
    )
