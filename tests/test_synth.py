"""Tests of torchfit.synth: the rasteriser and postures (fast), anny subjects (slow)."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest
from meshes import box_mesh

from torchfit.config import load_config
from torchfit.errors import ConfigError, ShapeError
from torchfit.synth.generate import SynthConfig
from torchfit.synth.postures import POSTURES, mirror, perturb, segment_rotations
from torchfit.synth.raster import rasterize, vertex_normals


def test_rasterize_nearer_triangle_wins():
    # two overlapping triangles; the one listed first is farther away
    pixels = np.array([[2, 2], [17, 2], [2, 17], [4, 4], [19, 4], [4, 19]], dtype=float)
    depth = np.array([5.0, 5.0, 5.0, 2.0, 2.0, 2.0])
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    r = rasterize(pixels, depth, faces, (24, 20))
    assert r.face[3, 3] == 0  # only the far triangle covers (3, 3)
    assert r.face[6, 6] == 1  # both cover (6, 6): the nearer wins
    assert r.depth[6, 6] == pytest.approx(2.0)
    assert r.face[0, 0] == -1 and np.isinf(r.depth[0, 0])
    # the same with the order of the faces reversed: still the nearer one
    r2 = rasterize(pixels, depth, faces[::-1].copy(), (24, 20))
    assert r2.face[6, 6] == 0 and r2.depth[6, 6] == pytest.approx(2.0)
    # crossing triangles: depth varies across, each wins where it is nearer
    depth3 = np.array([1.0, 1.0, 9.0, 9.0, 9.0, 1.0])
    r3 = rasterize(pixels, depth3, faces, (24, 20))
    assert r3.face[5, 12] == 0 and r3.face[14, 5] == 1


def test_rasterize_coverage_matches_naive_loop():
    rng = np.random.default_rng(0)
    pixels = rng.uniform(-3, 30, (30, 2))
    depth = rng.uniform(1, 3, 30)
    faces = rng.integers(0, 30, (20, 3))
    faces = faces[
        (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    ]
    r = rasterize(pixels, depth, faces, (28, 25), chunk=50)  # tiny chunks exercise the loop
    for y in range(25):
        for x in range(28):
            best, best_f = np.inf, -1
            for f, (a, b, c) in enumerate(faces):
                m = np.array([pixels[b] - pixels[a], pixels[c] - pixels[a]]).T
                if abs(np.linalg.det(m)) < 1e-12:
                    continue
                l1, l2 = np.linalg.solve(m, np.array([x, y]) - pixels[a])
                l0 = 1 - l1 - l2
                if min(l0, l1, l2) < -1e-9:
                    continue
                inv = l0 / depth[a] + l1 / depth[b] + l2 / depth[c]
                if 1 / inv < best:
                    best, best_f = 1 / inv, f
            if best_f >= 0:
                assert r.depth[y, x] == pytest.approx(best, rel=1e-9)
            else:
                assert r.face[y, x] == -1
    with pytest.raises(ShapeError, match=r"faces: expected shape \(F, 3\)"):
        rasterize(pixels, depth, faces[:, :2], (28, 25))


def test_vertex_normals_of_a_tetrahedron_point_outwards():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    n = vertex_normals(v, f)
    assert (np.sum(n * (v - v.mean(0)), 1) > 0).all()


def test_segment_rotations_follow_bap_semantics():
    down = np.array([0.0, 0.0, -1.0])
    rot = segment_rotations({"l_shoulder_abduct": 90, "r_shoulder_abduct": 90})
    np.testing.assert_allclose(rot["l_upper_arm"] @ down, [1, 0, 0], atol=1e-12)  # left is +x
    np.testing.assert_allclose(rot["r_upper_arm"] @ down, [-1, 0, 0], atol=1e-12)
    rot = segment_rotations({"l_shoulder_flexion": 90, "l_knee_flexion": 90})
    np.testing.assert_allclose(rot["l_upper_arm"] @ down, [0, -1, 0], atol=1e-12)  # forward -y
    np.testing.assert_allclose(rot["l_shank"] @ down, [0, 1, 0], atol=1e-12)  # backwards
    cactus = POSTURES[4]
    rot = segment_rotations({k: cactus.angle(k) for k in cactus.angles})
    for side in ("l", "r"):
        forearm = rot[f"{side}_upper_arm"] @ rot[f"{side}_forearm"] @ down
        np.testing.assert_allclose(forearm, [0, 0, 1], atol=1e-12)  # forearms point up
    r = segment_rotations({"l_hip_abduct": 30})["l_thigh"]
    np.testing.assert_allclose(mirror(mirror(r)), r)


def test_perturb_stays_within_bounds():
    rng = np.random.default_rng(3)
    for posture in POSTURES:
        for _ in range(20):
            angles = perturb(posture, rng, 10.0)
            for name, value in angles.items():
                assert abs(value - posture.angle(name)) <= 10.0 + 1e-12
            assert angles["l_knee_flexion"] >= 0 and angles["r_elbow_flexion"] >= 0
    assert [p.side_view for p in POSTURES] == [False, False, True, False, False, True]


def test_synth_config(tmp_path):
    path = tmp_path / "synth.yaml"
    path.write_text("noise_sigma: 1.0\nstereo: false\n")
    cfg = load_config(path, ["background_frames=6"], schema=SynthConfig)
    assert cfg.noise_sigma == 1.0 and not cfg.stereo and cfg.background_frames == 6
    assert cfg.image_size == [720, 576]
    path.write_text("noise: 1.0\n")
    with pytest.raises(ConfigError, match="unknown key 'noise'"):
        load_config(path, schema=SynthConfig)
    with pytest.raises(ConfigError, match="'background_frames' must be >= 5"):
        load_config(None, ["background_frames=3"], schema=SynthConfig)


# --------------------------------------------------------------------------------------------
# anny subjects (slow: about 20-40 s per subject on a laptop CPU, plus the first model build)


def _digest(folder) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.mark.slow
def test_generated_subject_is_valid_plausible_and_deterministic(tmp_path):
    pytest.importorskip("anny")
    from torchfit.io.dataset import load_dataset
    from torchfit.measurements import JOINT_NAMES, MEASUREMENT_KEYS
    from torchfit.synth.generate import make_subject

    cfg = SynthConfig(png_compression=1)
    make_subject(tmp_path / "a" / "s0", seed=7, index=0, cfg=cfg)
    make_subject(tmp_path / "b" / "s0", seed=7, index=0, cfg=cfg)
    assert _digest(tmp_path / "a" / "s0") == _digest(tmp_path / "b" / "s0")
    # evaluation masks: present, and --masks-only rewrites exactly the same files
    masks = {k: v for k, v in _digest(tmp_path / "a" / "s0").items() if "truth_masks" in k}
    assert len(masks) == 16  # 6 postures + 2 stereo views, person and shadow each
    make_subject(tmp_path / "c" / "s0", seed=7, index=0, cfg=cfg, masks_only=True)
    assert _digest(tmp_path / "c" / "s0") == masks

    (subject,) = load_dataset(tmp_path / "a")
    assert subject.ok, subject.problems
    assert subject.warnings == [] and subject.stereo is not None
    truth = subject.truth
    assert set(MEASUREMENT_KEYS) <= set(truth)
    assert 1.45 <= truth["height_m"] <= 2.05
    assert 0.9 <= truth["arm_span_m"] / truth["height_m"] <= 1.1
    assert 0.2 <= truth["lower_leg_m"] / truth["height_m"] <= 0.33
    assert 0.45 <= truth["virtual_leg_m"] / truth["height_m"] <= 0.6
    assert truth["upper_arm_m"] > truth["forearm_m"] * 0.8
    captures = truth["joints_world"]
    assert set(captures) == {f"pose{i}" for i in range(1, 7)} | {"stereo"}
    for joints in captures.values():
        assert set(joints) == set(JOINT_NAMES)
        assert min(j[2] for j in joints.values()) > 0  # above the floor
    # posture 3: left knee flexed backwards (ankle high), left side nearer the camera
    import torch

    from torchfit.camera import world_to_camera

    p3 = captures["pose3"]
    assert p3["l_ankle"][2] > p3["l_knee"][2] - 0.15
    pts = torch.tensor([p3["l_shoulder"], p3["r_shoulder"]], dtype=torch.float64)[None]
    depth = world_to_camera(pts, subject.camera)[0, :, 2]
    assert depth[0] < depth[1]
    p1 = captures["pose1"]
    pts = torch.tensor([p1["l_shoulder"], p1["r_shoulder"]], dtype=torch.float64)[None]
    depth = world_to_camera(pts, subject.camera)[0, :, 2]
    assert math.isclose(depth[0].item(), depth[1].item(), abs_tol=0.12)  # facing the camera
    summary = json.loads((tmp_path / "a" / "s0" / "synth.json").read_text())
    assert summary["height_m"] == truth["height_m"]


def test_render_body_occludes_room_and_casts_a_floor_shadow():
    from torchfit.camera import project_points
    from torchfit.synth.scene import Light, render, sample_camera, sample_room

    rng = np.random.default_rng(0)
    az = 2.0  # any azimuth: nothing assumes a world direction for the camera
    centre = np.array([3.5 * math.cos(az), 3.5 * math.sin(az), 1.3])
    room = sample_room(rng, az, 3.5)
    room.boxes = []
    room.pictures = []
    camera = sample_camera(rng, centre, np.array([0.0, 0.0, 1.0]), (180, 144), 2.8)
    # light from the camera's side, 70 degrees off: the shadow falls behind and beside the box
    light_dir = np.array([math.cos(az + 1.2), math.sin(az + 1.2), 1.0])
    light = Light(light_dir / np.linalg.norm(light_dir), ambient=0.45, diffuse=0.6)
    v, f = box_mesh((-0.2, -0.2, 0.0), (0.2, 0.2, 1.6))
    albedo = np.tile([0.1, 0.2, 0.8], (len(v), 1))
    empty = render(room, camera, light, None)
    full = render(room, camera, light, (v, f, albedo))
    # the box's centre pixel shows the box colour (blue), not the wall
    import torch

    u, vv = (
        project_points(torch.tensor([[[0.0, 0.0, 0.8]]], dtype=torch.float64), camera)[0, 0]
        .round()
        .long()
    )
    px = full[vv, u]
    assert px[2] > 2 * px[0]
    # the shadow of a point high on the box, on the floor beside it, is darker
    shadow_pt = np.array([0.0, 0.0, 1.2]) - 1.2 / light.direction[2] * light.direction
    su, sv = project_points(torch.tensor(shadow_pt)[None, None], camera)[0, 0].round().long()
    before, after = empty[sv, su], full[sv, su]
    ratio = after / before
    assert (ratio < 0.8).all()
    np.testing.assert_allclose(ratio, ratio.mean(), rtol=1e-6)  # same hue, only darker


def test_render_layers_give_the_true_person_and_shadow_masks(tmp_path):
    import cv2
    import torch

    from torchfit.camera import project_points
    from torchfit.synth.generate import _write_mask
    from torchfit.synth.scene import (
        Light,
        body_coverage,
        render,
        room_depth,
        sample_camera,
        sample_room,
    )

    rng = np.random.default_rng(1)
    az = 0.7
    centre = np.array([3.5 * math.cos(az), 3.5 * math.sin(az), 1.3])
    room = sample_room(rng, az, 3.5)
    room.boxes = []
    camera = sample_camera(rng, centre, np.array([0.0, 0.0, 1.0]), (180, 144), 2.8)
    light_dir = np.array([math.cos(az + 1.2), math.sin(az + 1.2), 1.0])
    light = Light(light_dir / np.linalg.norm(light_dir), ambient=0.45, diffuse=0.6)
    v, f = box_mesh((-0.2, -0.2, 0.0), (0.2, 0.2, 1.6))
    albedo = np.tile([0.1, 0.2, 0.8], (len(v), 1))
    colour, person, shadow = render(room, camera, light, (v, f, albedo), layers=True)
    np.testing.assert_array_equal(colour, render(room, camera, light, (v, f, albedo)))
    empty = render(room, camera, light, None)
    # the person mask is exactly where the body was painted over the room
    changed = np.abs(colour - empty).max(-1) > 0
    assert person.any() and (changed[person]).all()
    np.testing.assert_array_equal(
        person, body_coverage(camera, v, f, room_depth(room, camera, light))
    )
    # the shadow mask: outside the person, darker floor, the same hue
    assert shadow.sum() > 20 and not (shadow & person).any()
    ratio = colour[shadow] / empty[shadow]
    assert (ratio < 0.9).all()
    np.testing.assert_allclose(ratio, np.repeat(ratio[:, :1], 3, 1), rtol=1e-6)
    pt = np.array([0.0, 0.0, 1.2]) - 1.2 / light.direction[2] * light.direction
    su, sv = project_points(torch.tensor(pt)[None, None], camera)[0, 0].round().long()
    assert shadow[sv, su]
    # written as a 0/255 single-channel PNG
    _write_mask(tmp_path / "m" / "pose1.png", person, 3)
    back = cv2.imread(str(tmp_path / "m" / "pose1.png"), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint8 and back.ndim == 2 and set(np.unique(back)) == {0, 255}
    np.testing.assert_array_equal(back > 0, person)


def test_green_screen_room_and_spill():
    import numpy as np

    from torchfit.synth.greenscreen import SCREEN_GREEN, add_spill, green_screen
    from torchfit.synth.room import sample_room

    room = sample_room(np.random.default_rng(0), 0.3, 3.5)
    green_screen(room)
    assert np.allclose(room.wall_colour, SCREEN_GREEN) and room.boxes == [] and not room.skirting
    colour = np.full((30, 30, 3), 0.3)
    person = np.zeros((30, 30), bool)
    person[5:25, 5:25] = True
    out = add_spill(colour, person, 0.5)
    assert out[5, 15, 1] > out[10, 15, 1] >= out[15, 15, 1] == 0.3  # strongest on the edge
    assert np.array_equal(out[:, :, [0, 2]], colour[:, :, [0, 2]])
    assert np.array_equal(out[~person], colour[~person])
