"""Tracked joints against a sequence's truth (``eval.json``), and a fitted model with a
synthetic body's true skeleton lengths (``tools/track.py --true-skeleton``)."""

from __future__ import annotations

import numpy as np
import torch

from torchfit.body.model import BodyModel
from torchfit.camera import Camera, world_to_camera
from torchfit.errors import DataError
from torchfit.measurements import JOINT_NAMES

__all__ = ["joint_errors", "skeleton_scales"]

#: segment whose scale a true limb length sets -> (its joint, the joint at its far end).
_LIMBS = {
    "{s}_upperarm": ("{s}_shoulder", "{s}_elbow"),
    "{s}_forearm": ("{s}_elbow", "{s}_wrist"),
    "{s}_thigh": ("{s}_hip", "{s}_knee"),
    "{s}_calf": ("{s}_knee", "{s}_ankle"),
}


def joint_errors(tracked: list[dict], truth: list[dict], camera: Camera | None = None) -> dict:
    """Mean per-joint position error (mm) over frames, head_top excluded.

    With the sequence's ``camera`` it also splits each error along the camera's ray through
    the true joint (``along_ray_mm``: the depth one view hardly shows, mean of its absolute
    value; ``along_ray_signed_mm``: negative towards the camera) and across it
    (``across_ray_mm``: what the image shows).
    """
    names = [n for n in JOINT_NAMES if n != "head_top"]
    got = np.array([[f[n] for n in names] for f in tracked], dtype=np.float64)
    want = np.array([[t[n] for n in names] for t in truth], dtype=np.float64)
    if got.shape != want.shape:
        raise DataError(f"{len(tracked)} tracked frames against {len(truth)} truth frames")
    err = np.linalg.norm(got - want, axis=-1) * 1000
    out = {
        "mean_joint_error_mm": float(err.mean()),
        "per_joint_mm": {n: float(err[:, k].mean()) for k, n in enumerate(names)},
        "per_frame_mm": [round(float(v), 1) for v in err.mean(1)],
    }
    if camera is not None:
        cam = camera.to(dtype=torch.float64)
        a = world_to_camera(torch.from_numpy(got), cam).numpy()
        b = world_to_camera(torch.from_numpy(want), cam).numpy()
        ray = b / np.linalg.norm(b, axis=-1, keepdims=True)
        along = ((a - b) * ray).sum(-1)
        across = np.linalg.norm(a - b - along[..., None] * ray, axis=-1)
        out["along_ray_mm"] = float(np.abs(along).mean() * 1000)
        out["along_ray_signed_mm"] = float(along.mean() * 1000)
        out["across_ray_mm"] = float(across.mean() * 1000)
    return out


def skeleton_scales(
    model: BodyModel, scales: dict[str, list[float]], joints: dict[str, list[float]]
) -> dict[str, list[float]]:
    """Fitted scales with a body's true skeleton lengths (a synthetic subject's
    ``truth.json`` joints of one capture): each limb segment's scale along its bone (z) set
    so its joint-to-joint length is the true one, the spine segments' z by the true
    back-to-neck length over the fitted, the pelvis across (y) by the true hip width over the
    fitted; the segments' thickness stays the fit's.

    Args:
        model: the body model.
        scales: the fit's ``segment_scales`` (params.json).
        joints: true joint positions of one capture.

    Returns:
        segment -> [sx, sy, sz], as ``params.json``'s ``segment_scales``.
    """
    t = model.template
    sc = torch.tensor([scales[n] for n in t.segments], dtype=model.dtype)
    with torch.no_grad():
        zero = {k: v for k, v in model.zeros(1).items() if k != "scales"}
        fitted = model.joint_positions(model(sc[None], **zero))
    fj = {k: v[0].numpy() for k, v in fitted.items()}
    true = {k: np.asarray(v, dtype=np.float64) for k, v in joints.items()}
    ratio = lambda a, b: float(  # noqa: E731
        np.linalg.norm(true[b] - true[a]) / np.linalg.norm(fj[b] - fj[a])
    )
    out = {n: list(map(float, sc[i])) for i, n in enumerate(t.segments)}
    for side in ("l", "r"):
        for seg, (a, b) in _LIMBS.items():
            name = seg.format(s=side)
            if name in out:
                out[name][2] *= ratio(a.format(s=side), b.format(s=side))
    spine = ratio("back", "neck")
    for name in t.segments:
        if t.parents[t.segments.index(name)] < 0 or name in ("l5", "t10", "t1", "torso"):
            out[name][2] *= spine
    out[t.segments[0]][1] *= ratio("l_hip", "r_hip")
    return out
