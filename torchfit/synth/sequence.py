"""A test sequence from real motion: one anny body, its six postures, and a clip of it moving.

:func:`make_sequence` writes

- ``<out>/subject/``: subject 0 of ``seed`` exactly as :func:`torchfit.synth.generate.make_subject`
  writes it (six postures, truth), so the body model can be fitted first;
- ``<out>/sequence/``: the same body in the same room, light and camera, moving as the clip
  (:mod:`torchfit.synth.mocap`): ``camera.yaml``, ``background/bg01.png`` …,
  ``frames/000000.png`` …, ``truth_masks/000000.png`` … (evaluation only),
  ``truth.json`` = ``{"fps": F, "joints_world": [{joint: [x, y, z], …}, …]}`` (design.md's
  joints, world frame, metres) and ``synth.json`` (what made it: the clip, its frames, the
  seed).

Placement: the torso moves as the capture's (its frame from the hips and the neck); the clip is
turned about the vertical so that the body faces the camera at its first frame (plus a random
turn within ±25°), its hip trajectory is scaled by the ratio of the body's leg length to the
capture's, starts above the origin, and is shrunk horizontally (the same factor for the whole
clip) until it stays within ``max_travel_m`` of its start, so the person stays in the camera's
view (a clip that travels further is played more in place, the feet sliding somewhat).

Height: the body stands on the floor as the captured person does. The capture's floor level is
the 5th percentile, over the whole capture, of its lower ankle's height (the ankle's height
when a foot stands on the floor); in each frame the body's lowest point is as far above the
floor as the capture's lower ankle is above that level, times the leg-length ratio (0 while a
foot is down, the jump's height in the air). The capture's hip height is not used: the body's
legs are not the captured person's, and lifting the hips by the capture's would float the feet
or sink them into the floor.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from torchfit.errors import DataError
from torchfit.io.camera import save_camera
from torchfit.measurements import JOINT_NAMES
from torchfit.synth.generate import (
    _background_gain,
    _write_mask,
    _write_png,
    make_subject,
    subject_scene,
)
from torchfit.synth.mocap import load_mocap, retarget
from torchfit.synth.options import SynthConfig
from torchfit.synth.postures import axis_angle
from torchfit.synth.scene import finish, render

__all__ = ["make_sequence"]

_TURN_DEG = 25.0


def _leg(joints: dict[str, np.ndarray]) -> float:
    return sum(
        float(np.linalg.norm(joints[f"{s}_{b}"] - joints[f"{s}_{a}"]))
        for s in ("l", "r")
        for a, b in (("hip", "knee"), ("knee", "ankle"))
    )


def _floor_level(joints: dict[str, np.ndarray]) -> float:
    """The capture's floor level: the 5th percentile of its lower ankle's height over all its
    frames, metres (see the module doc)."""
    lower = np.minimum(joints["l_ankle"][:, 2], joints["r_ankle"][:, 2])
    return float(np.percentile(lower, 5))


def make_sequence(
    out: str | Path,
    clip: str | Path,
    frames: int,
    seed: int,
    start: int = 0,
    step: int = 1,
    cfg: SynthConfig | None = None,
    model: Any = None,
    progress: Callable[[Iterable[int]], Iterable[int]] | None = None,
    max_travel_m: float = 0.6,
) -> dict:
    """Write ``<out>/subject`` and ``<out>/sequence`` (see the module doc).

    Args:
        out: output folder.
        clip: a CMU ``.bvh`` or ``.amc`` file.
        frames: number of frames to render.
        seed: the subject's seed (body, room, camera, turn).
        start: first clip frame, counted from the clip's first frame of motion (a rest pose
            the file starts with is not one, :func:`torchfit.synth.mocap.load_mocap`).
        step: clip frames between rendered frames (the sequence's rate is the clip's / step).
        cfg: synthesis options (defaults when None).
        model: an anny model.
        progress: wraps the frame indices (e.g. ``tqdm``).
        max_travel_m: the largest horizontal distance of the hips from their start.

    Returns:
        A summary (fps, frames, clip range, subject summary).

    Raises:
        DataError: the clip is too short or the arguments are out of range.
    """
    cfg = cfg or SynthConfig()
    out = Path(out)
    if frames < 1 or step < 1 or start < 0:
        raise DataError(
            f"frames and step must be >= 1 and start >= 0, got {frames}, {step}, {start}"
        )
    mocap = load_mocap(clip)
    last = start + (frames - 1) * step
    if last >= mocap.num_frames:
        raise DataError(
            f"{clip}: has {mocap.num_frames} frames, frame {last} needed "
            f"(start {start} + ({frames} - 1) x step {step})"
        )
    summary = make_subject(out / "subject", seed, 0, cfg, model)
    scene = subject_scene(seed, 0, cfg, model)
    rng = np.random.default_rng([seed, 1_000_003])
    body = scene.body
    neutral = body.pose({})
    picks = [start + k * step for k in range(frames)]
    clip_joints = [{n: v[i] for n, v in mocap.joints.items()} for i in picks]
    ratio = _leg(neutral.joints) / _leg(clip_joints[0])
    # turn: the first frame's forward (-y of the torso frame, horizontal) towards the camera
    first, _ = retarget(clip_joints[0])
    fwd = -first[:, 1]
    heading = math.atan2(fwd[1], fwd[0])
    turn = scene.facing - heading + math.radians(rng.uniform(-_TURN_DEG, _TURN_DEG))
    yaw = axis_angle((0, 0, 1), turn)
    origin = clip_joints[0]["back"] * np.array([1.0, 1.0, 0.0])
    travel = max(float(np.linalg.norm((j["back"] - origin)[:2])) * ratio for j in clip_joints)
    shrink = min(1.0, max_travel_m / travel) if travel > 0 else 1.0
    squash = np.array([shrink, shrink, 1.0])
    level = _floor_level(mocap.joints)
    feet = body.foot_directions()
    posed_frames = []
    for joints in clip_joints:
        frame, segments = retarget(joints, feet)
        posed = body.pose({}, segments)
        rot = yaw @ frame
        hips = yaw @ (squash * ratio * (joints["back"] - origin))
        verts = (posed.vertices - posed.joints["back"]) @ rot.T + hips
        named = {k: rot @ (v - posed.joints["back"]) + hips for k, v in posed.joints.items()}
        ankle = min(float(joints["l_ankle"][2]), float(joints["r_ankle"][2]))
        lift = np.array([0.0, 0.0, ratio * max(0.0, ankle - level) - float(verts[:, 2].min())])
        posed_frames.append((verts + lift, {k: v + lift for k, v in named.items()}))
    seq = out / "sequence"
    empty = render(scene.room, scene.camera, scene.light, None)
    for i in range(cfg.background_frames):
        img = finish(empty, rng, _background_gain(rng), cfg.noise_sigma)
        _write_png(seq / "background" / f"bg{i + 1:02d}.png", img, cfg.png_compression)
    truth = []
    indices: Iterable[int] = range(frames) if progress is None else progress(range(frames))
    for k in indices:
        verts, named = posed_frames[k]
        colour, person, _ = render(
            scene.room,
            scene.camera,
            scene.light,
            (verts, scene.faces, scene.albedo),
            layers=True,
        )
        gain = 1 + rng.uniform(-cfg.illumination_change, cfg.illumination_change)
        img = finish(colour, rng, gain + np.zeros(3), cfg.noise_sigma)
        _write_png(seq / "frames" / f"{k:06d}.png", img, cfg.png_compression)
        _write_mask(seq / "truth_masks" / f"{k:06d}.png", person, cfg.png_compression)
        truth.append({n: [round(float(x), 5) for x in named[n]] for n in JOINT_NAMES})
    save_camera(scene.camera, seq / "camera.yaml")
    fps = 1.0 / (mocap.frame_time * step)
    (seq / "truth.json").write_text(json.dumps({"fps": fps, "joints_world": truth}, indent=1))
    made = {
        "clip": str(clip),
        "start": start,
        "rest_frames_skipped": mocap.skipped,
        "step": step,
        "frames": frames,
        "fps": fps,
        "horizontal_shrink": round(shrink, 3),
        "seed": seed,
    }
    (seq / "synth.json").write_text(json.dumps(made, indent=1))
    return {**made, "subject": summary}
