"""The hard rooms of the synthetic generator: defaults unchanged, shadow map, conditions."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import pytest
from meshes import box_mesh

from torchfit.config import load_config
from torchfit.errors import ConfigError
from torchfit.synth.hard import HardConditions
from torchfit.synth.options import SynthConfig
from torchfit.synth.scene import Light, finish, render, sample_camera, sample_room
from torchfit.synth.shadow import shadow_map_test

REPO = Path(__file__).resolve().parents[1]


def _scene(seed: int, az: float, size=(96, 80)):
    rng = np.random.default_rng(seed)
    centre = np.array([3.5 * math.cos(az), 3.5 * math.sin(az), 1.3])
    room = sample_room(rng, az, 3.5)
    camera = sample_camera(rng, centre, np.array([0.0, 0.0, 1.0]), size, 2.8)
    d = np.array([math.cos(az + 1.2), math.sin(az + 1.2), 1.0])
    light = Light(d / np.linalg.norm(d), ambient=0.45, diffuse=0.6)
    return rng, room, camera, light


def test_default_render_is_unchanged():
    # The standard room must render bit-identically to the renderer before the hard rooms
    # (today's datasets stay reproducible). Reference: this scene rendered and finished by
    # torchfit at commit b1e3c2c (main, before the hard rooms), numpy 2 / OpenCV 4 on CPU.
    rng, room, camera, light = _scene(5, 2.0)
    assert len(room.boxes) == 2 and len(room.pictures) == 2
    v, f = box_mesh((-0.2, -0.2, 0.0), (0.2, 0.2, 1.6))
    albedo = np.tile([0.1, 0.2, 0.8], (len(v), 1))
    colour, person, cast = render(room, camera, light, (v, f, albedo), layers=True)
    img = finish(colour, rng, np.array([1.01, 0.99, 1.0]), 2.0)
    digest = hashlib.sha256(img.tobytes() + person.tobytes() + cast.tobytes()).hexdigest()
    assert digest == "982c60acbbf2df23738a09b0c73e33e9b2a3156d2c8282de39d6c68c0fc5df1b"


def _ray_hits(v, f, origin, direction):
    """Naive reference: does the ray origin + t * direction (t > 0) cross any triangle?
    (Moeller-Trumbore, one triangle at a time.)"""
    for a, b, c in f:
        e1, e2 = v[b] - v[a], v[c] - v[a]
        p = np.cross(direction, e2)
        det = e1 @ p
        if abs(det) < 1e-12:
            continue
        s = origin - v[a]
        u = (s @ p) / det
        q = np.cross(s, e1)
        w = (direction @ q) / det
        t = (e2 @ q) / det
        if u >= 0 and w >= 0 and u + w <= 1 and t > 1e-9:
            return True
    return False


def test_shadow_map_matches_naive_ray_casting():
    v, f = box_mesh((-0.2, -0.15, 0.5), (0.25, 0.2, 1.4))
    light = np.array([0.5, -0.3, 0.6])
    light /= np.linalg.norm(light)
    rng = np.random.default_rng(0)
    # points on a wall behind the box (x = -1), on the floor, and a few in front of the light
    pts = np.concatenate(
        [
            np.stack([np.full(300, -1.0), rng.uniform(-1, 1.5, 300), rng.uniform(0, 2, 300)], 1),
            np.stack([rng.uniform(-1, 0.5, 300), rng.uniform(-1, 1.5, 300), np.zeros(300)], 1),
            np.array([[1.0, 0.0, 1.0], [np.nan, np.nan, np.nan]]),
        ]
    )
    got = shadow_map_test(v, f, light, pts, texel_m=0.002, bias_m=1e-3)
    want = np.array([np.isfinite(p).all() and _ray_hits(v, f, p, light) for p in pts])
    assert want.sum() > 40 and (~want).sum() > 40
    # the shadow map and the rays agree except within a texel or two of the shadow's edge
    disagree = got != want
    assert disagree.sum() <= 0.02 * len(pts)
    assert not got[-2:].any()
    assert got.shape == (len(pts),)
    np.testing.assert_array_equal(
        shadow_map_test(v, f, light, pts.reshape(2, -1, 3)[..., :], texel_m=0.002, bias_m=1e-3),
        got.reshape(2, -1),
    )


def test_all_surfaces_shadow_falls_on_the_back_wall():
    rng, room, camera, light = _scene(1, 0.7, size=(180, 144))
    room.boxes, room.pictures = [], []
    room.back = 0.8
    az = room.azimuth + math.radians(30)  # low light from the camera's side
    d = np.array([math.cos(az) * math.cos(0.4), math.sin(az) * math.cos(0.4), math.sin(0.4)])
    light = Light(d, ambient=0.3, diffuse=0.7)
    v, f = box_mesh((-0.2, -0.2, 0.0), (0.2, 0.2, 1.6))
    albedo = np.tile([0.1, 0.2, 0.8], (len(v), 1))
    body = (v, f, albedo)
    empty = render(room, camera, light, None)
    floor_only, _, cast_floor = render(room, camera, light, body, layers=True)
    colour, person, cast = render(room, camera, light, body, layers=True, all_surfaces=True)
    assert not (cast & person).any()
    # the wall shadow is new: pixels darker than the empty room that the floor shadow missed
    wall = cast & ~cast_floor
    assert wall.sum() > 100
    ratio = colour[wall] / empty[wall]
    assert (ratio < 0.8).all()
    np.testing.assert_allclose(ratio, np.repeat(ratio[:, :1], 3, 1), rtol=1e-6)  # same hue
    # outside the cast shadow and the person the room is as it was (up to the blur's tail)
    outside = ~cast & ~person
    assert np.abs(colour[outside] - empty[outside]).max() < 0.25
    assert (np.abs(colour[outside] - empty[outside]).max(-1) < 1e-6).mean() > 0.9
    np.testing.assert_array_equal(floor_only[person], colour[person])


def test_conditions_all_off_change_nothing():
    cfg = SynthConfig()
    hard = HardConditions(cfg, 3, 1, 11)
    rng, room, camera, light = _scene(2, 1.0)
    before = (room.back, [b.lo.copy() for b in room.boxes], room.pattern, list(room.posters))
    assert hard.scene(room, light) is light
    assert (room.back, room.pattern, room.posters) == (before[0], None, [])
    assert all((b.lo == lo).all() for b, lo in zip(room.boxes, before[1], strict=True))
    assert not hard.changes_gain and not hard.all_surfaces
    img = np.random.default_rng(0).integers(0, 256, (8, 8, 3), dtype=np.uint8)
    assert hard.encode(img) is img


def test_each_condition_changes_only_itself():
    def scene(**keys):
        cfg = SynthConfig(**keys)
        _, room, _, light = _scene(2, 1.0)
        return room, HardConditions(cfg, 3, 1, 11).scene(room, light)

    base_room, base_light = scene()
    room, light = scene(textures=True)
    assert room.pattern is not None and len(room.posters) >= 2 and room.pictures == []
    assert light is not base_light and (light.direction == base_light.direction).all()
    assert room.back == base_room.back and len(room.boxes) == len(base_room.boxes)
    room, light = scene(furniture=True)
    assert {b.texture for b in room.boxes} >= {"books", "door", "cabinet"}
    assert room.pattern is None and (light.direction == base_light.direction).all()
    room, light = scene(wall_shadows=True)
    assert 0.7 <= room.back <= 1.2 and math.asin(light.direction[2]) < math.radians(36)
    assert room.pattern is None and len(room.boxes) == len(base_room.boxes)
    # the same furniture whether or not the walls are textured (separate random streams)
    a, _ = scene(furniture=True)
    b, _ = scene(furniture=True, textures=True)
    assert [x.hi.tolist() for x in a.boxes] == [x.hi.tolist() for x in b.boxes]


def test_exposure_and_jpeg():
    cfg = SynthConfig(exposure_change=0.1, white_balance=0.06, exposure_drift=0.05)
    hard = HardConditions(cfg, 0, 0, 11)
    gains = np.array([hard.posture_gain(k) for k in range(5, 11)])
    assert hard.changes_gain and (np.abs(gains - 1) <= 1.1 * 1.06 * 1.05 - 1 + 1e-12).all()
    assert np.ptp(gains, 0).min() > 0.01  # changes between postures
    assert np.abs(hard.background_gain(0) - 1).max() == 0  # the drift starts at zero
    img = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    out = HardConditions(SynthConfig(jpeg_quality=[75, 75]), 0, 0, 11).encode(img)
    assert out.shape == img.shape and out.dtype == np.uint8 and (out != img).any()


def test_hard_config_file_and_errors():
    cfg = load_config(REPO / "configs" / "synth_hard.yaml", schema=SynthConfig)
    assert cfg.wall_shadows and cfg.furniture and cfg.textures and cfg.jpeg_quality == [75, 90]
    assert cfg.exposure_change > 0 and cfg.white_balance > 0 and cfg.exposure_drift > 0
    with pytest.raises(ConfigError, match="'jpeg_quality' expects"):
        load_config(None, ["jpeg_quality=[90, 75]"], schema=SynthConfig)
    with pytest.raises(ConfigError, match="'white_balance' must be in"):
        load_config(None, ["white_balance=0.7"], schema=SynthConfig)


# --------------------------------------------------------------------------------------------
# anny subjects (slow)


def _folder_digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(folder)).encode())
            h.update(hashlib.sha256(p.read_bytes()).digest())
    return h.hexdigest()


@pytest.mark.slow
def test_default_subject_is_unchanged(tmp_path):
    # Reference: every file of this subject as written by main at commit b1e3c2c (before the
    # hard rooms), same environment (anny, numpy, OpenCV on CPU).
    pytest.importorskip("anny")
    from torchfit.synth.generate import make_subject

    make_subject(tmp_path / "s0", seed=7, index=0, cfg=SynthConfig(image_size=[180, 144]))
    assert len(list((tmp_path / "s0").rglob("*.png"))) == 39
    digest = _folder_digest(tmp_path / "s0")
    assert digest == "ce189a751d594aa8791237315c43ebba89bdd0e50efb65f5198a1361e9d137e1"


@pytest.mark.slow
def test_hard_subject_masks_only_and_shadow_truth(tmp_path):
    pytest.importorskip("anny")
    from torchfit.synth.generate import make_subject

    cfg = load_config(
        REPO / "configs" / "synth_hard.yaml", ["image_size=[240, 192]"], schema=SynthConfig
    )
    make_subject(tmp_path / "a" / "s0", seed=3, index=0, cfg=cfg)
    make_subject(tmp_path / "c" / "s0", seed=3, index=0, cfg=cfg, masks_only=True)
    masks = sorted((tmp_path / "c" / "s0").rglob("*.png"))
    assert len(masks) == 16
    for m in masks:
        rel = m.relative_to(tmp_path / "c" / "s0")
        assert m.read_bytes() == (tmp_path / "a" / "s0" / rel).read_bytes(), rel
