"""The live guidance page of tools/capture.py --device, with a video file standing in for the
camera (the demo subject's frames: the empty room, then its six posture images held)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchfit.io.images import list_images, read_image

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "data" / "demo" / "subject_000"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _video(path: Path) -> Path:
    frames = [read_image(p) for p in list_images(DEMO / "background")] * 2
    for k in range(1, 7):
        frames += [read_image(DEMO / "poses" / f"pose{k}.png")] * 14
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
    for frame in frames:
        writer.write(np.ascontiguousarray(frame[:, :, ::-1]))
    writer.release()
    return path


@pytest.fixture
def live(tmp_path):
    """The tool running on the stand-in video; yields (url, process, out folder)."""
    video = _video(tmp_path / "camera.avi")
    cmd = [
        sys.executable,
        str(REPO / "tools" / "capture.py"),
        "--device",
        str(video),
        "--camera",
        str(DEMO / "camera.yaml"),
        "--out",
        str(tmp_path / "subject"),
        "--port",
        "0",
        "--linger",
        "120",
        "--hold-frames",
        "3",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()
        assert line.startswith("guidance at http://127.0.0.1:"), line + proc.stderr.read()
        yield line.split()[-1], proc, tmp_path / "subject"
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def _status(url: str) -> dict:
    with urllib.request.urlopen(url + "status.json", timeout=10) as reply:
        return json.loads(reply.read())


def _wait_for_score(url: str, timeout: float = 120.0) -> dict:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        status = _status(url)
        if status["score"] is not None:
            return status
        time.sleep(0.3)
    raise AssertionError(f"no score on the page after {timeout} s: {status}")


@pytest.mark.slow
def test_page_serves_frame_status_and_captures(live):
    url, proc, out = live
    assert url.startswith("http://127.0.0.1:")
    with urllib.request.urlopen(url, timeout=10) as reply:
        assert b"frame.png" in reply.read()
    status = _wait_for_score(url)
    assert status["message"].startswith("strike posture")
    with urllib.request.urlopen(url + "frame.png", timeout=10) as reply:
        frame = cv2.imdecode(np.frombuffer(reply.read(), np.uint8), cv2.IMREAD_COLOR)
    assert frame.shape == (576, 720, 3)
    green = (frame[:, :, 1] > 200) & (frame[:, :, 0] < 60) & (frame[:, :, 2] < 60)
    assert green.sum() > 300  # the template contour
    # the demo's own posture images held for 1.4 s each: the first postures get captured
    end = time.monotonic() + 180
    while time.monotonic() < end and "pose1" not in _status(url)["captured"]:
        time.sleep(0.5)
    assert (out / "poses" / "pose1.png").is_file()
    assert len(list((out / "background").iterdir())) == 10
    # the image is the median of the hold's last 3 frames (the same image, so all agree)
    pose1 = json.loads((out / "capture.json").read_text())["postures"]["pose1"]
    last = pose1["frame"]
    assert pose1["combined_frames"] == [last - 2, last - 1, last]
    assert pose1["frame_cut"] == []
    assert 10 <= last < 24  # within posture 1's 14 frames after the 10 background ones


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed")
def test_page_in_a_headless_browser(live, tmp_path):
    url, _, _ = live
    _wait_for_score(url)
    flags = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--no-first-run",
        f"--user-data-dir={tmp_path / 'profile'}",
        "--window-size=800,760",
        "--virtual-time-budget=3000",
    ]
    shot = tmp_path / "page.png"
    subprocess.run(
        [CHROMIUM, *flags, f"--screenshot={shot}", url], capture_output=True, timeout=120
    )
    image = cv2.imread(str(shot))
    assert image is not None, "no screenshot"
    green = (image[:, :, 1] > 200) & (image[:, :, 0] < 80) & (image[:, :, 2] < 80)
    assert green.sum() > 200  # the template contour over the live frame
    # the frame itself: far more distinct colours than the page's dark background and text
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 2000
    dom = subprocess.run(
        [CHROMIUM, *flags, "--dump-dom", url], capture_output=True, text=True, timeout=120
    ).stdout
    assert "strike posture" in dom and "score: 0." in dom
