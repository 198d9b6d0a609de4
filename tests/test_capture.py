"""Guided capture from a video (torchfit.capture.offline, tools/capture.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from torchfit.capture.offline import (
    CaptureOptions,
    capture_from_frames,
    choose_frames,
    held_frames,
    match_score,
    median_frame,
    still_stretches,
    template_silhouettes,
)

REPO = Path(__file__).resolve().parents[1]


def test_choose_frames_keeps_the_postures_order_and_names_the_missing():
    # stretch 1 matches posture 2 best, but posture 1 must come first
    scores = np.array(
        [
            [0.8, 0.6, 0.1, 0.1, 0.1, 0.1, 0.1],
            [0.7, 0.9, 0.1, 0.1, 0.1, 0.1, 0.1],
            [0.1, 0.1, 0.8, 0.1, 0.1, 0.1, 0.1],
            [0.1, 0.1, 0.1, 0.2, 0.3, 0.1, 0.1],  # posture 4 is not in the video
            [0.1, 0.1, 0.1, 0.1, 0.9, 0.1, 0.1],
            [0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.7],
        ]
    )
    assert choose_frames(scores, 0.5) == [0, 1, 2, None, 4, 6]
    assert choose_frames(np.zeros((6, 0)), 0.5) == [None] * 6


def test_still_stretches():
    masks = torch.zeros(12, 10, 10, dtype=torch.bool)
    masks[:, 2:8, 4:6] = True
    masks[5, 2:8, 2:8] = True  # a movement at frame 5
    masks[9:, 0:9, 0:9] = True  # another posture from frame 9
    runs = still_stretches(masks, 100, CaptureOptions(min_still=3))
    assert runs == [(100, 104), (106, 108), (109, 111)]


def test_match_score_aligns_feet_and_height():
    template = np.zeros((100, 80), bool)
    template[20:90, 30:40] = True
    person = np.zeros((100, 80), bool)
    person[5:75, 50:60] = True  # the same shape higher up and to the right
    assert match_score(person, template, rescale=False) == pytest.approx(1.0)
    tall = np.zeros((100, 80), bool)
    tall[0:98, 48:62] = True  # 1.4 times as tall and wide
    assert match_score(tall, template) > 0.9
    assert match_score(tall, template, rescale=False) < 0.6


def _held_video(moved: int) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
    """12 frames of a grey rectangle on a dark scene with sensor noise (sigma 6 grey levels);
    frame ``moved`` has the rectangle shifted. Returns frames (uint8), masks, the clean
    image."""
    clean = np.full((40, 30, 3), 40, np.uint8)
    clean[5:35, 10:20] = 180
    rng = np.random.default_rng(3)
    frames, masks = [], []
    for i in range(12):
        image = clean.copy()
        mask = np.zeros((40, 30), bool)
        mask[5:35, 10:20] = True
        if i == moved:
            image = np.full_like(clean, 40)
            image[5:35, 13:23] = 180
            mask = np.zeros((40, 30), bool)
            mask[5:35, 13:23] = True
        noisy = np.clip(np.round(image + rng.normal(0, 6, image.shape)), 0, 255)
        frames.append(noisy.astype(np.uint8))
        masks.append(mask)
    return torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2), np.stack(masks), clean


def test_held_frames_are_contiguous_and_leave_out_a_moved_frame():
    frames, masks, clean = _held_video(moved=7)
    # around frame 5: 6 is taken, 7 moved so the run stops there (8.. are not taken even
    # though they agree again); before it, 4, 3, 2 until 5 frames
    assert held_frames(masks, 5, 0, 11, 5, 0.97) == [2, 3, 4, 5, 6]
    assert held_frames(masks, 5, 0, 11, 9, 0.97) == [0, 1, 2, 3, 4, 5, 6]
    assert held_frames(masks, 5, 3, 11, 9, 0.97) == [3, 4, 5, 6]  # the stretch's bounds
    assert held_frames(masks, 5, 0, 11, 1, 0.97) == [5]
    assert held_frames(masks, 7, 0, 11, 5, 0.97) == [7]  # nothing agrees with the moved one
    # a loose overlap takes the moved frame (IoU 0.54): alternately after and before
    assert held_frames(masks, 5, 0, 11, 9, 0.5) == list(range(1, 10))
    single = median_frame(frames, [5])
    assert np.array_equal(single, frames[5].permute(1, 2, 0).numpy())
    combined = median_frame(frames, [0, 1, 2, 3, 4, 5, 6])
    error = lambda image: np.abs(image.astype(float) - clean).mean()  # noqa: E731
    assert error(combined) < 0.6 * error(single)
    # an even count: the mean of the two middle values; float frames in [0, 1] alike
    assert np.array_equal(median_frame(frames.float() / 255, [0, 1, 2, 3, 4, 5, 6]), combined)
    pair = median_frame(frames, [0, 1]).astype(int)
    expected = np.round(frames[:2].double().mean(0).permute(1, 2, 0).numpy())
    assert np.array_equal(pair, expected)


def test_capture_combines_the_held_frames_of_each_posture():
    """A video painted from the six template silhouettes, each held 7 frames with sensor
    noise; in posture 3's hold the last two frames have a hand moved (a box beside the
    silhouette: still by the still-stretch test, below the overlap asked of combined frames)."""
    from torchfit.body.model import BodyModel
    from torchfit.config import Config
    from torchfit.io.camera import camera_from_dict

    camera = camera_from_dict(
        {
            "image_size": [180, 144],
            "K": [[196.0, 0.0, 90.0], [0.0, 196.0, 72.0], [0.0, 0.0, 1.0]],
            "dist": [0.0, 0.0, 0.0, 0.0, 0.0],
            "R": [[-0.2424, 0.9702, 0.0], [0.1028, 0.0257, -0.9944], [-0.9647, -0.2411, -0.106]],
            "t": [0.03, 1.02, 3.69],
        }
    )
    model = BodyModel(Config().model.template)
    templates = template_silhouettes(model, camera)
    rng = np.random.default_rng(5)
    scene = rng.uniform(60, 120, (144, 180, 3))
    person = np.array([200.0, 40.0, 40.0])

    def frame(mask):
        image = np.where(mask[..., None], person, scene) + rng.normal(0, 2, scene.shape)
        return np.clip(np.round(image), 0, 255).astype(np.uint8)

    moved = templates[2].copy()
    rows, cols = np.nonzero(moved)
    middle = (rows.min() + rows.max()) // 2
    right = np.nonzero(moved[middle])[0].max()
    moved[middle - 3 : middle + 4, right + 1 : right + 11] = True  # 70 pixels, 6 % of the area
    frames = [frame(np.zeros((144, 180), bool)) for _ in range(8)]
    holds = {}
    for k in range(1, 7):
        holds[k] = (len(frames), len(frames) + 6)
        for i in range(7):
            frames.append(frame(moved if k == 3 and i >= 5 else templates[k - 1]))
        frames.append(frame(np.zeros((144, 180), bool)))  # between postures: out of view
    video = torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2).contiguous()
    # a noise frame's overlap with the chosen one is 0.98 or more, the moved ones' 0.94
    options = CaptureOptions(still_change=0.08, hold_frames=7, hold_iou=0.97)
    result = capture_from_frames(video, camera, model, options=options)
    assert result.missing == []
    assert result.stretches == list(holds.values())
    for k in range(1, 7):
        first, last = holds[k]
        expected = list(range(first, last - 1 if k == 3 else last + 1))
        assert result.combined[k] == expected, k
        assert result.chosen[k] in expected
    # one frame each: today's behaviour
    options = CaptureOptions(still_change=0.08, hold_frames=1)
    single = capture_from_frames(video, camera, model, options=options)
    assert all(single.combined[k] == [single.chosen[k]] for k in range(1, 7))


@pytest.mark.slow
def test_capture_picks_a_frame_inside_each_held_stretch(tmp_path):
    pytest.importorskip("anny")
    from torchfit.synth.options import SynthConfig
    from torchfit.synth.video import make_video

    doc = make_video(tmp_path / "video", 7001, SynthConfig(stereo=False, image_size=[400, 320]))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable,
        str(REPO / "tools" / "capture.py"),
        "--video",
        str(tmp_path / "video" / "frames"),
        "--camera",
        str(tmp_path / "video" / "camera.yaml"),
        "--out",
        str(tmp_path / "subject"),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    capture = json.loads((tmp_path / "subject" / "capture.json").read_text())
    for k in range(1, 7):
        first, last = doc["holds"][f"pose{k}"]
        assert first <= capture["postures"][f"pose{k}"]["frame"] <= last
        assert capture["postures"][f"pose{k}"]["frame_cut"] == []  # inside the picture
    assert "the image frame cuts" not in done.stderr
    assert capture["background_frames"][-1] <= doc["empty"][1]
    from torchfit.io.dataset import load_subject

    assert load_subject(tmp_path / "subject").ok

    # without posture 4's held stretch: named in the error, the others written
    frames = tmp_path / "no_t_pose"
    frames.mkdir()
    first, last = doc["holds"]["pose4"]
    for path in sorted((tmp_path / "video" / "frames").iterdir()):
        if not first - 3 <= int(path.stem) <= last + 3:
            os.symlink(path, frames / path.name)
    cmd[cmd.index("--video") + 1] = str(frames)
    cmd[cmd.index("--out") + 1] = str(tmp_path / "partial")
    done = subprocess.run(cmd, capture_output=True, text=True, env=env)
    assert done.returncode == 1
    assert "not found in the video: pose4 (t_pose)" in done.stderr
    written = sorted(p.name for p in (tmp_path / "partial" / "poses").iterdir())
    assert written == ["pose1.png", "pose2.png", "pose3.png", "pose5.png", "pose6.png"]


@pytest.mark.slow
def test_capture_video_of_a_dataset_subject(tmp_path):
    """make_video(subject=(seed, index)) films that subject: the body and camera of
    make_subject's folder; original_clean/ is original/ without the sensor noise."""
    pytest.importorskip("anny")
    from torchfit.io.images import read_image
    from torchfit.synth.generate import make_subject
    from torchfit.synth.options import SynthConfig
    from torchfit.synth.video import make_video

    cfg = SynthConfig(stereo=False, image_size=[160, 128])
    make_subject(tmp_path / "subject", 1000, 2, cfg)
    make_video(tmp_path / "video", 1000, cfg, fps=3.0, subject=(1000, 2))
    video, subject = tmp_path / "video", tmp_path / "subject"
    assert (video / "camera.yaml").read_text() == (subject / "camera.yaml").read_text()
    truth = json.loads((subject / "truth.json").read_text())
    measured = json.loads((video / "truth.json").read_text())
    assert measured and all(truth[key] == value for key, value in measured.items())
    for k in range(1, 7):
        noisy = read_image(tmp_path / "video" / "original" / "poses" / f"pose{k}.png")
        clean = read_image(tmp_path / "video" / "original_clean" / "poses" / f"pose{k}.png")
        difference = np.abs(noisy.astype(float) - clean).mean()
        assert 0.5 < difference < 4.0  # sensor noise of 2 grey levels, nothing else
