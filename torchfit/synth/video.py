"""A synthetic capture video: the empty scene, then a subject walking onto the mark and striking
the six postures of design.md section 4 in order, each held still for a while, with
interpolated transitions (a stand-in camera for ``tools/capture.py``).

Written to a folder: ``frames/000000.png`` …, ``camera.yaml``, ``truth.json`` and
``video.json`` (the frame rate and, per posture, the first and last frame of its held
stretch), and beside them ``original/``: a subject folder (design.md section 3) whose
background frames are the first empty frames and whose ``poses/pose<k>.png`` is the middle
frame of posture k's held stretch, the images a capture should reproduce, and
``original_clean/``: the same with each posture image rendered without sensor noise (the
background frames as in ``original/``).

The subject is drawn from the seed, or (``subject=(seed, index)``) is subject ``index`` of a
dataset made with that seed (:func:`torchfit.synth.generate.subject_scene`): the same body,
clothes, room, light and camera as that subject folder.

A held posture is perfectly still: its frames differ only by sensor noise.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from torchfit.io.camera import save_camera
from torchfit.synth.body import load_anny
from torchfit.synth.generate import _place, _truth, _write_png, outward_faces, subject_scene
from torchfit.synth.options import SynthConfig
from torchfit.synth.postures import POSTURES, axis_angle, perturb
from torchfit.synth.room import Light
from torchfit.synth.scene import finish, render, sample_camera, sample_room
from torchfit.synth.subject import body_with_height, sample_albedo, sample_phenotype

__all__ = ["make_video"]


def _blend(a: dict[str, float], b: dict[str, float], s: float) -> dict[str, float]:
    return {k: (1 - s) * a.get(k, 0.0) + s * b.get(k, 0.0) for k in set(a) | set(b)}


def make_video(
    folder: str | Path,
    seed: int,
    cfg: SynthConfig | None = None,
    fps: float = 6.0,
    empty_s: float = 1.5,
    walk_s: float = 1.0,
    hold_s: float = 1.2,
    transition_s: float = 0.8,
    model: Any = None,
    subject: tuple[int, int] | None = None,
) -> dict:
    """Write a synthetic capture video and its original subject folder.

    Args:
        folder: the output folder (created).
        seed: the subject and scene are drawn from ``default_rng([seed, 0])``.
        cfg: generator options (image size, noise, camera ranges).
        fps: frames per second.
        empty_s, walk_s, hold_s, transition_s: the empty start, the walk onto the mark, each
            held posture and each transition between postures, seconds.
        model: an anny model (default: :func:`torchfit.synth.body.load_anny`).
        subject: ``(dataset seed, index)``: film that dataset subject (its body, room, light
            and camera; ``cfg`` must be the dataset's) instead of one drawn from ``seed``.

    Returns:
        The ``video.json`` document.
    """
    cfg = cfg or SynthConfig(stereo=False)
    folder = Path(folder)
    size = (int(cfg.image_size[0]), int(cfg.image_size[1]))
    if subject is not None:
        scene = subject_scene(subject[0], subject[1], cfg, model or load_anny())
        rng, body, faces, albedo = scene.rng, scene.body, scene.faces, scene.albedo
        room, light, camera, facing = scene.room, scene.light, scene.camera, scene.facing
        azimuth = scene.azimuth
        horiz = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    else:
        rng = np.random.default_rng([seed, 0])
        phen, _ = sample_phenotype(rng)
        body = body_with_height(phen, rng.uniform(*cfg.height_range_m), model or load_anny())
        faces = outward_faces(body)
        albedo = sample_albedo(body, rng)
        azimuth = rng.uniform(0, 2 * math.pi)
        distance = rng.uniform(*cfg.camera_distance_m)
        room = sample_room(rng, azimuth, distance)
        light_dir = np.array([math.cos(azimuth + 0.6), math.sin(azimuth + 0.6), 1.6])
        light = Light(light_dir / np.linalg.norm(light_dir), ambient=0.45, diffuse=0.6)
        horiz = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
        centre = horiz * distance + np.array([0.0, 0.0, rng.uniform(*cfg.camera_height_m)])
        camera = sample_camera(rng, centre, np.array([0.0, 0.0, 1.0]), size, 2.8)
        facing = math.atan2(centre[1], centre[0])
    side = np.cross([0.0, 0.0, 1.0], horiz)  # the person walks in from the side

    # key poses: angles, yaw, floor offset
    keys = []
    for posture in POSTURES:
        angles = perturb(posture, rng, cfg.joint_noise_deg)
        yaw = facing - (math.pi / 2 if posture.side_view else 0.0)
        keys.append((angles, yaw, rng.uniform(-cfg.floor_offset_m, cfg.floor_offset_m, 2)))
    stand = keys[0][0]

    n_empty, n_walk = round(empty_s * fps), round(walk_s * fps)
    n_hold, n_move = round(hold_s * fps), round(transition_s * fps)
    states: list[tuple[dict[str, float], float, np.ndarray] | None] = [None] * n_empty
    start = keys[0][2] + 2.2 * side[:2]
    for i in range(n_walk):
        s = (i + 1) / n_walk
        states.append((stand, facing, (1 - s) * start + s * keys[0][2]))
    holds = {}
    previous = (stand, facing, keys[0][2])
    for k, key in enumerate(keys, start=1):
        if k > 1:
            for i in range(n_move):
                s = (i + 1) / (n_move + 1)
                s = 0.5 - 0.5 * math.cos(math.pi * s)
                states.append(
                    (
                        _blend(previous[0], key[0], s),
                        (1 - s) * previous[1] + s * key[1],
                        (1 - s) * previous[2] + s * key[2],
                    )
                )
        holds[f"pose{k}"] = [len(states), len(states) + n_hold - 1]
        states += [key] * n_hold
        previous = key
    states += [keys[-1]] * round(0.5 * fps)

    frames_dir = folder / "frames"
    empty = render(room, camera, light, None)
    rendered: dict[int, np.ndarray] = {}
    for index, state in enumerate(states):
        if state is None:
            colour = empty
        else:
            key_id = id(state)
            if key_id not in rendered:
                angles, yaw, offset = state
                rotation = axis_angle((0, 0, 1), yaw + math.pi / 2)
                posed = _place(body.pose(angles), rotation, np.asarray(offset))
                rendered[key_id] = render(room, camera, light, (posed.vertices, faces, albedo))
            colour = rendered[key_id]
        image = finish(colour, rng, np.ones(3), cfg.noise_sigma)
        _write_png(frames_dir / f"{index:06d}.png", image, cfg.png_compression)
    save_camera(camera, folder / "camera.yaml")
    truth = _truth(body)
    (folder / "truth.json").write_text(json.dumps(truth, indent=1))

    for name, clean in (("original", False), ("original_clean", True)):
        original = folder / name
        for i in range(min(n_empty, 5)):
            data = (frames_dir / f"{i:06d}.png").read_bytes()
            (original / "background").mkdir(parents=True, exist_ok=True)
            (original / "background" / f"bg{i + 1:02d}.png").write_bytes(data)
        (original / "poses").mkdir(parents=True, exist_ok=True)
        for pose, (a, b) in holds.items():
            path = original / "poses" / f"{pose}.png"
            if clean:  # no noise drawn: the video's random stream is left as it was
                colour = rendered[id(states[(a + b) // 2])]
                image = finish(colour, np.random.default_rng(0), np.ones(3), 0.0)
                _write_png(path, image, cfg.png_compression)
            else:
                path.write_bytes((frames_dir / f"{(a + b) // 2:06d}.png").read_bytes())
        save_camera(camera, original / "camera.yaml")
        (original / "truth.json").write_text(json.dumps(truth, indent=1))
    doc = {"fps": fps, "frames": len(states), "empty": [0, n_empty - 1], "holds": holds}
    (folder / "video.json").write_text(json.dumps(doc, indent=1))
    return doc
