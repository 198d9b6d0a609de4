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

from torchfit.capture.offline import CaptureOptions, choose_frames, match_score, still_stretches

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
