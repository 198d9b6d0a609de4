"""Write synthetic subject folders (design.md section 3) from anny bodies.

One subject: a random phenotype (sex, adult age, height 1.50–2.00 m, thin to heavy), clothing
and skin colours, a room, a light and a camera 3–4 m away at chest height at a random azimuth;
the six postures of design.md section 4 (every free joint off nominal by up to ±10°, floor
offset up to ±5 cm, yaw ±5°, lean ±2°), background frames, ``camera.yaml``, ``truth.json``
(measurements of design.md section 5 via :func:`torchfit.measurements.measurements_from_joints`
and ``joints_world`` per capture) and the stereo pair of design.md section 7. Subject ``i`` of
seed ``S`` is drawn from ``numpy.random.default_rng([S, i])``: the same seed gives the same
subjects, whatever ``n``.

**Evaluation-only masks.** Like ``truth.json``, the folder ``truth_masks/`` is ground truth
for evaluation, never an input of the fit (the dataset loader does not read it):
``truth_masks/pose1.png`` … ``pose6.png`` hold the true person silhouette of each posture
image (0/255, the renderer's own coverage: pixel centres covered by a visible body triangle,
before the optics blur), ``truth_masks/pose1_shadow.png`` … the body's cast shadow outside
the person (where the blurred shadow reaches at least half strength): on the floor in the
standard rooms, on every surface it darkens (floor, walls, furniture) with ``wall_shadows``
(:mod:`torchfit.synth.hard`); ``stereo/truth_masks/``
holds ``left.png``, ``right.png``, ``left_shadow.png`` and ``right_shadow.png``.
``make_subject(..., masks_only=True)`` rewrites only these masks for an existing subject: it
draws the same random numbers in the same order without rendering the empty room, writing
the images or building the noise images' pixels, so the masks equal a full run's.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from torchfit.camera import look_at
from torchfit.io.camera import save_camera, save_stereo_cameras
from torchfit.measurements import JOINT_NAMES, measurements_from_joints
from torchfit.synth.body import AnnyBody, PosedBody, load_anny
from torchfit.synth.greenscreen import add_spill, green_screen, no_green
from torchfit.synth.hard import HardConditions
from torchfit.synth.options import SynthConfig
from torchfit.synth.postures import POSTURES, STEREO_POSTURE, Posture, axis_angle, perturb
from torchfit.synth.scene import Light, Room, finish, render, sample_camera, sample_room
from torchfit.synth.subject import body_with_height, sample_albedo, sample_phenotype

__all__ = [
    "SynthConfig",
    "SubjectScene",
    "make_subject",
    "make_subjects",
    "outward_faces",
    "sample_phenotype",
    "subject_scene",
]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Subjects


def _placement(rng: np.random.Generator, facing: float, cfg: SynthConfig) -> np.ndarray:
    """(3, 3) rotation of a capture: yaw so anny's forward (-y) points along ``facing``
    (plus jitter), then a small lean about a random horizontal axis."""
    yaw = facing + math.radians(rng.uniform(-cfg.yaw_deg, cfg.yaw_deg))
    Rz = axis_angle((0, 0, 1), yaw + math.pi / 2)
    tilt_axis = rng.uniform(0, 2 * math.pi)
    lean = axis_angle(
        (math.cos(tilt_axis), math.sin(tilt_axis), 0.0),
        math.radians(rng.uniform(-cfg.lean_deg, cfg.lean_deg)),
    )
    return lean @ Rz


def _place(posed: PosedBody, rotation: np.ndarray, offset: np.ndarray) -> PosedBody:
    v = posed.vertices @ rotation.T
    shift = np.array([offset[0], offset[1], -v[:, 2].min()])
    return PosedBody(
        vertices=v + shift,
        joints={k: rotation @ j + shift for k, j in posed.joints.items()},
    )


def _capture(
    body: AnnyBody, posture: Posture, facing: float, rng: np.random.Generator, cfg: SynthConfig
) -> tuple[PosedBody, dict[str, float]]:
    angles = perturb(posture, rng, cfg.joint_noise_deg)
    if posture.side_view:
        facing = facing - math.pi / 2  # turned 90 degrees to the body's right
    rotation = _placement(rng, facing, cfg)
    offset = rng.uniform(-cfg.floor_offset_m, cfg.floor_offset_m, size=2)
    return _place(body.pose(angles), rotation, offset), angles


def _truth(body: AnnyBody) -> dict[str, float]:
    neutral = _place(body.pose({}), np.eye(3), np.zeros(2))
    height = float(neutral.vertices[:, 2].max())
    t_pose = body.pose({"l_shoulder_abduct": 90.0, "r_shoulder_abduct": 90.0}).vertices
    span = float(t_pose[:, 0].max() - t_pose[:, 0].min())
    joints = {k: torch.tensor(v, dtype=torch.float64)[None] for k, v in neutral.joints.items()}
    values = measurements_from_joints(
        joints,
        torch.tensor([height], dtype=torch.float64),
        torch.tensor([span], dtype=torch.float64),
    )
    return {k: round(float(v[0]), 5) for k, v in values.items()}


def _joints_json(posed: PosedBody) -> dict[str, list[float]]:
    return {name: [round(float(x), 5) for x in posed.joints[name]] for name in JOINT_NAMES}


def _sample_light(rng: np.random.Generator, azimuth: float) -> Light:
    """Light from the camera's side, 20-60 degrees off its azimuth, 50-65 degrees high: the
    shadow falls on the floor behind and beside the person."""
    light_az = azimuth + rng.choice([-1, 1]) * math.radians(rng.uniform(20, 60))
    light_el = math.radians(rng.uniform(50, 65))
    direction = np.array(
        [
            math.cos(light_az) * math.cos(light_el),
            math.sin(light_az) * math.cos(light_el),
            math.sin(light_el),
        ]
    )
    return Light(direction, ambient=rng.uniform(0.4, 0.5), diffuse=rng.uniform(0.55, 0.7))


def _background_gain(rng: np.random.Generator) -> np.ndarray:
    """(3,) per-channel gain of one background frame (slight flicker between frames)."""
    return 1 + rng.normal(0, 0.004, 3)


def _write_png(path: Path, rgb: np.ndarray, compression: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), rgb[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, compression]):
        raise OSError(f"cannot write {path}")


def _write_mask(path: Path, mask: np.ndarray, compression: int) -> None:
    """Write a (H, W) bool mask as a 0/255 single-channel PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    data = np.where(mask, 255, 0).astype(np.uint8)
    if not cv2.imwrite(str(path), data, [cv2.IMWRITE_PNG_COMPRESSION, compression]):
        raise OSError(f"cannot write {path}")


def _skip_finish(rng: np.random.Generator, shape: tuple[int, ...], noise_sigma: float) -> None:
    """Draw exactly the random numbers :func:`finish` draws for an image of ``shape``
    (its sensor noise), without forming the image: keeps ``masks_only`` runs in step."""
    rng.normal(0.0, noise_sigma, shape)


def _write_stereo(
    stereo: Path,
    body: AnnyBody,
    faces: np.ndarray,
    albedo: np.ndarray,
    room: Room,
    light: Light,
    azimuth: float,
    rng: np.random.Generator,
    cfg: SynthConfig,
    masks_only: bool = False,
    hard: HardConditions | None = None,
) -> dict[str, list[float]]:
    """The stereo pair of design.md section 7 (posture 5, two parallel cameras ``baseline``
    apart, within 10 degrees of the main camera's azimuth) and its truth masks; returns its
    joints_world. ``masks_only`` writes only ``stereo/truth_masks``."""
    st_az = azimuth + math.radians(rng.uniform(-10, 10))
    st_dist = rng.uniform(*cfg.camera_distance_m)
    baseline = rng.uniform(*cfg.stereo_baseline_m)
    st_horiz = np.array([math.cos(st_az), math.sin(st_az), 0.0])
    rig = st_horiz * st_dist + np.array([0.0, 0.0, rng.uniform(*cfg.camera_height_m)])
    st_target = np.array([0.0, 0.0, rng.uniform(1.0, 1.15)])
    R, _ = look_at(torch.from_numpy(rig)[None], torch.from_numpy(st_target)[None])
    right_axis = R[0, 0].numpy()  # camera x: image right
    view_h = rng.uniform(2.7, 3.0)
    size = (int(cfg.image_size[0]), int(cfg.image_size[1]))
    cams = {}
    for side, sign in (("left", -1.0), ("right", 1.0)):
        c = rig + sign * 0.5 * baseline * right_axis
        cams[side] = sample_camera(
            rng, c, st_target + sign * 0.5 * baseline * right_axis, size, view_h
        )
    posed, _ = _capture(body, STEREO_POSTURE, math.atan2(rig[1], rig[0]), rng, cfg)
    gain = 1 + rng.uniform(-cfg.illumination_change, cfg.illumination_change, 1) + np.zeros(3)
    hard = hard or HardConditions(cfg, 0, 0, 1)
    if hard.changes_gain:
        gain = gain * hard.posture_gain(hard.captures)
    shape = (size[1], size[0], 3)
    for side, cam in cams.items():
        empty = None if masks_only else render(room, cam, light, None)
        for i in range(cfg.background_frames):
            bg_gain = _background_gain(rng)
            if masks_only:
                _skip_finish(rng, shape, cfg.noise_sigma)
                continue
            if hard.changes_gain:
                bg_gain = bg_gain * hard.background_gain(i)
            _write_png(
                stereo / "background" / side / f"bg{i + 1:02d}.png",
                hard.encode(finish(empty, rng, bg_gain, cfg.noise_sigma)),
                cfg.png_compression,
            )
        colour, person, cast = render(
            room,
            cam,
            light,
            (posed.vertices, faces, albedo),
            layers=True,
            all_surfaces=hard.all_surfaces,
        )
        _write_mask(stereo / "truth_masks" / f"{side}.png", person, cfg.png_compression)
        _write_mask(stereo / "truth_masks" / f"{side}_shadow.png", cast, cfg.png_compression)
        if masks_only:
            _skip_finish(rng, shape, cfg.noise_sigma)
            continue
        _write_png(
            stereo / f"{side}.png",
            hard.encode(finish(colour, rng, gain, cfg.noise_sigma)),
            cfg.png_compression,
        )
    if not masks_only:
        save_stereo_cameras(cams["left"], cams["right"], stereo / "cameras.yaml")
    return _joints_json(posed)


@dataclass
class SubjectScene:
    """The random draws of subject ``index`` of seed ``seed`` before its captures: body,
    colours, room, light, camera (``rng`` is left where the captures continue)."""

    rng: np.random.Generator
    body: AnnyBody
    faces: np.ndarray
    albedo: np.ndarray
    size: tuple[int, int]
    sex: str
    phenotype: Any
    azimuth: float
    room: Room
    light: Light
    hard: HardConditions
    camera: Any
    facing: float


def outward_faces(body: Any) -> np.ndarray:
    """The body's triangles, counter-clockwise seen from outside (outward normals): flipped
    when the rest pose's signed volume is negative."""
    faces = body.faces
    v = body.pose({}).vertices
    volume = np.einsum("ij,ij->i", v[faces[:, 0]], np.cross(v[faces[:, 1]], v[faces[:, 2]])).sum()
    return faces[:, ::-1].copy() if volume < 0 else faces


def subject_scene(seed: int, index: int, cfg: SynthConfig, model: Any = None) -> SubjectScene:
    """Draw subject ``index`` of seed ``seed``: the same body, room, light and camera as
    :func:`make_subject` (which calls it), e.g. to film that body in motion."""
    rng = np.random.default_rng([seed, index])
    size = (int(cfg.image_size[0]), int(cfg.image_size[1]))
    phen, sex = sample_phenotype(rng)
    lo, hi = cfg.height_range_m
    target = (
        rng.uniform(lo, min(hi, lo + 0.35))
        if sex == "female"
        else rng.uniform(max(lo, hi - 0.4), hi)
    )
    body = body_with_height(phen, target, model)
    faces = outward_faces(body)
    albedo = sample_albedo(body, rng)
    if cfg.green_screen:
        albedo = no_green(albedo)

    azimuth = rng.uniform(0, 2 * math.pi)
    distance = rng.uniform(*cfg.camera_distance_m)
    cam_h = rng.uniform(*cfg.camera_height_m)
    room = sample_room(rng, azimuth, distance)
    light = _sample_light(rng, azimuth)
    hard = HardConditions(cfg, seed, index, cfg.background_frames + len(POSTURES))
    light = hard.scene(room, light)  # the hard rooms' conditions (unchanged when all off)
    if cfg.green_screen:
        green_screen(room)
    horiz = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    centre = horiz * distance + np.array([0.0, 0.0, cam_h])
    target_pt = np.array([*rng.uniform(-0.05, 0.05, 2), rng.uniform(0.95, 1.05)])
    camera = sample_camera(rng, centre, target_pt, size, rng.uniform(2.6, 2.9))
    facing = math.atan2(centre[1], centre[0])

    return SubjectScene(
        rng, body, faces, albedo, size, sex, phen, azimuth, room, light, hard, camera, facing
    )


def make_subject(
    folder: str | Path,
    seed: int,
    index: int,
    cfg: SynthConfig | None = None,
    model: Any = None,
    masks_only: bool = False,
) -> dict:
    """Generate and write one subject folder.

    Args:
        folder: the subject folder to write (created).
        seed, index: the subject is drawn from ``default_rng([seed, index])``.
        cfg: options (defaults when None).
        model: an anny model (default: :func:`torchfit.synth.body.load_anny`).
        masks_only: write only ``truth_masks/`` (and ``stereo/truth_masks/``), the same files
            a full run writes, for a subject generated before the masks existed; images,
            cameras, ``truth.json`` and ``synth.json`` are left as they are.

    Returns:
        A summary: phenotype, sex, camera azimuth and the truth measurements.
    """
    cfg = cfg or SynthConfig()
    folder = Path(folder)
    sc = subject_scene(seed, index, cfg, model)
    rng, body, faces, albedo, size = sc.rng, sc.body, sc.faces, sc.albedo, sc.size
    sex, phen, azimuth = sc.sex, sc.phenotype, sc.azimuth
    room, light, hard, camera, facing = sc.room, sc.light, sc.hard, sc.camera, sc.facing

    truth = _truth(body)
    joints_world = {}
    shape = (size[1], size[0], 3)
    empty = None if masks_only else render(room, camera, light, None)
    for i in range(cfg.background_frames):
        bg_gain = _background_gain(rng)
        if masks_only:
            _skip_finish(rng, shape, cfg.noise_sigma)
            continue
        if hard.changes_gain:
            bg_gain = bg_gain * hard.background_gain(i)
        img = hard.encode(finish(empty, rng, bg_gain, cfg.noise_sigma))
        _write_png(folder / "background" / f"bg{i + 1:02d}.png", img, cfg.png_compression)
    for posture in POSTURES:
        posed, _ = _capture(body, posture, facing, rng, cfg)
        joints_world[f"pose{posture.index}"] = _joints_json(posed)
        colour, person, cast = render(
            room,
            camera,
            light,
            (posed.vertices, faces, albedo),
            layers=True,
            all_surfaces=hard.all_surfaces,
        )
        if cfg.green_screen:
            colour = add_spill(colour, person, cfg.spill)
        name = f"pose{posture.index}"
        _write_mask(folder / "truth_masks" / f"{name}.png", person, cfg.png_compression)
        _write_mask(folder / "truth_masks" / f"{name}_shadow.png", cast, cfg.png_compression)
        gain = (
            1
            + rng.uniform(-cfg.illumination_change, cfg.illumination_change)
            + rng.normal(0, 0.005, 3)
        )
        if hard.changes_gain:
            gain = gain * hard.posture_gain(cfg.background_frames + posture.index - 1)
        if masks_only:
            _skip_finish(rng, shape, cfg.noise_sigma)
            continue
        img = hard.encode(finish(colour, rng, gain, cfg.noise_sigma))
        _write_png(folder / "poses" / f"{name}.png", img, cfg.png_compression)
    if not masks_only:
        save_camera(camera, folder / "camera.yaml")

    if cfg.stereo:
        joints_world["stereo"] = _write_stereo(
            folder / "stereo", body, faces, albedo, room, light, azimuth, rng, cfg, masks_only, hard
        )

    truth["joints_world"] = joints_world
    summary = {
        "subject": folder.name,
        "seed": seed,
        "index": index,
        "sex": sex,
        "phenotype": phen.as_dict(),
        "camera_azimuth_deg": round(math.degrees(azimuth) % 360, 2),
        **{k: v for k, v in truth.items() if k != "joints_world"},
    }
    if not masks_only:
        (folder / "truth.json").write_text(json.dumps(truth, indent=1))
        (folder / "synth.json").write_text(json.dumps(summary, indent=1))
    log.debug("wrote %s: %s", folder, summary)
    return summary


def make_subjects(
    out: str | Path,
    n: int,
    seed: int,
    cfg: SynthConfig | None = None,
    progress: Callable[[Iterable[int]], Iterable[int]] | None = None,
) -> list[dict]:
    """Write ``n`` subjects ``subject_000`` … into ``out``.

    Args:
        out: the dataset folder.
        n: number of subjects.
        seed: dataset seed; subject ``i`` is drawn from ``default_rng([seed, i])``.
        cfg: options (defaults when None).
        progress: wraps the subject indices (e.g. ``tqdm``).

    Returns:
        The summaries of :func:`make_subject`.
    """
    model = load_anny()
    out = Path(out)
    indices: Iterable[int] = range(n) if progress is None else progress(range(n))
    return [make_subject(out / f"subject_{i:03d}", seed, i, cfg, model) for i in indices]
