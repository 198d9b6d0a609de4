"""Live guidance while capturing (first paper, section 9): the camera image with the target
posture's template contour drawn over it and the match score, served as a small web page on
the loopback interface only (``http://127.0.0.1:PORT``; the OpenCV build has no windows).

The page (``/``) shows ``/frame.png`` (the latest annotated frame) and ``/status.json``
(the posture to strike, its score, what was captured), refreshed a few times a second.

The loop: the first ``background_frames`` frames are the empty scene (the person stays out of
view); then each frame is segmented, the silhouette is scored against the current posture's
template (:func:`torchfit.capture.offline.match_score`); when the score stays at least
``min_score`` for ``hold_s`` seconds the posture is captured (``poses/pose<k>.png``) and the
next posture is the target. The image written is the per-pixel median of the last frames of
that hold, up to ``options.hold_frames``, contiguous and each with a silhouette overlapping the
last frame's by at least ``options.hold_iou`` (:func:`torchfit.capture.offline.held_frames`;
``hold_frames`` 1: the last frame itself). ``capture.json`` records, per posture, the frame
captured and the frames combined (counted from the first frame read).
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import cv2
import numpy as np
import torch

from torchfit.body.model import BodyModel
from torchfit.camera import Camera
from torchfit.capture.offline import (
    CaptureOptions,
    held_frames,
    match_score,
    median_frame,
    template_silhouettes,
)
from torchfit.errors import DataError
from torchfit.image.background import fit_background
from torchfit.image.plausibility import cut_borders
from torchfit.image.segment import SegmentationOptions, segment
from torchfit.io.camera import save_camera
from torchfit.io.files import write_atomic
from torchfit.io.images import write_image

__all__ = ["GuidanceServer", "run_live", "POSTURE_NAMES"]

POSTURE_NAMES = ("stand", "straddle", "side_knee", "t_pose", "cactus", "side_stand")

PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>torchfit capture</title>
<style>body{font-family:sans-serif;background:#222;color:#eee;margin:12px}
#score{font-size:28px}#frame{max-width:100%;border:2px solid #555}</style></head>
<body><h1 id="target">waiting for the camera</h1>
<div id="score">score: -</div><div id="info"></div>
<img id="frame" src="/frame.png" alt="live frame">
<script>
async function tick(){
  try{
    const s = await (await fetch('/status.json', {cache:'no-store'})).json();
    document.getElementById('target').textContent = s.message;
    document.getElementById('score').textContent =
      'score: ' + (s.score === null ? '-' : s.score.toFixed(2)) + ' (capture at ' +
      s.min_score.toFixed(2) + ', held ' + s.hold_s + ' s)';
    document.getElementById('info').textContent = 'captured: ' + s.captured.join(', ');
    document.getElementById('frame').src = '/frame.png?t=' + Date.now();
  }catch(e){}
}
setInterval(tick, 250); tick();
</script></body></html>
"""


class GuidanceServer:
    """The guidance page on ``127.0.0.1`` (``port`` 0 picks a free one)."""

    def __init__(self, port: int = 0) -> None:
        self._lock = threading.Lock()
        self._png = cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))[1].tobytes()
        self._status: dict = {
            "message": "waiting",
            "score": None,
            "min_score": 0.0,
            "hold_s": 0.0,
            "captured": [],
        }
        server = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 - the http.server API
                path = self.path.split("?", 1)[0]
                if path == "/":
                    body, kind = PAGE.encode(), "text/html; charset=utf-8"
                elif path == "/frame.png":
                    with server._lock:
                        body, kind = server._png, "image/png"
                elif path == "/status.json":
                    with server._lock:
                        body, kind = json.dumps(server._status).encode(), "application/json"
                else:
                    self.send_error(404)
                    return
                self.send_response(200)
                self.send_header("Content-Type", kind)
                self.send_header("Cache-Control", "no-store")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args: object) -> None:
                return

        self.httpd = ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self.port = self.httpd.server_address[1]
        self._thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        """The page's address."""
        return f"http://127.0.0.1:{self.port}/"

    def publish(self, frame_rgb: np.ndarray, status: dict) -> None:
        """Show a new annotated frame (H, W, 3) RGB uint8 and status."""
        png = cv2.imencode(".png", np.ascontiguousarray(frame_rgb[:, :, ::-1]))[1].tobytes()
        with self._lock:
            self._png = png
            self._status = dict(status)

    def close(self) -> None:
        """Stop serving."""
        self.httpd.shutdown()
        self.httpd.server_close()


def _annotate(frame: np.ndarray, template: np.ndarray, score: float | None, text: str):
    out = frame.copy()
    contours, _ = cv2.findContours(
        template.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
    )
    cv2.drawContours(out, contours, -1, (0, 255, 0), 2, cv2.LINE_AA)
    label = text if score is None else f"{text}  score {score:.2f}"
    cv2.putText(out, label, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 0), 2, cv2.LINE_AA)
    return out


def run_live(
    source: int | str,
    camera: Camera,
    model: BodyModel,
    out: Path,
    server: GuidanceServer,
    height_m: float | None = None,
    segmentation: SegmentationOptions | None = None,
    options: CaptureOptions | None = None,
    background_frames: int = 10,
    hold_s: float = 1.0,
    realtime: bool = True,
) -> list[int]:
    """Guide and capture from a camera (``source`` an OpenCV device number) or a video file
    standing in for one. Writes ``out/background``, ``out/poses`` and ``out/camera.yaml`` as
    they are captured; returns the postures captured.

    Raises:
        DataError: the source cannot be opened or its frames have the wrong size.
    """
    options = options or CaptureOptions()
    segmentation = segmentation or SegmentationOptions()
    video = cv2.VideoCapture(source)
    if not video.isOpened():
        raise DataError(f"cannot open the camera or video {source!r}")
    fps = video.get(cv2.CAP_PROP_FPS) or 10.0
    w, h = camera.image_size
    templates = template_silhouettes(model, camera, height_m)
    empty: list[np.ndarray] = []
    model_bg = None
    target, held, captured = 1, 0, []
    # the last frames of the current hold, (frame number, frame, mask): only these can be combined
    hold: deque[tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=options.hold_frames)
    record: dict[str, dict] = {}
    save_camera(camera, out / "camera.yaml")
    number = -1
    while target <= 6:
        ok, bgr = video.read()
        if not ok:
            break
        number += 1
        frame = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        if frame.shape[:2] != (h, w):
            raise DataError(
                f"camera frames are {frame.shape[1]}x{frame.shape[0]} pixels, "
                f"camera.yaml image_size is {w}x{h}"
            )
        status = {
            "min_score": options.min_score,
            "hold_s": hold_s,
            "captured": [f"pose{k}" for k in captured],
            "score": None,
        }
        if model_bg is None:
            empty.append(frame)
            write_image(out / "background" / f"bg{len(empty):02d}.png", frame)
            status["message"] = f"stay out of view: background {len(empty)}/{background_frames}"
            if len(empty) == background_frames:
                stack = torch.from_numpy(np.stack(empty)).permute(0, 3, 1, 2).float() / 255
                model_bg = fit_background(stack, segmentation)
            server.publish(_annotate(frame, templates[target - 1], None, status["message"]), status)
        else:
            image = torch.from_numpy(frame).permute(2, 0, 1)[None].float() / 255
            mask = segment(image, model_bg, segmentation).masks[0, 0].numpy()
            score = match_score(mask, templates[target - 1], height_m is None)
            if score >= options.min_score:
                held += 1
                hold.append((number, frame, mask))
            else:
                held = 0
                hold.clear()
            name = POSTURE_NAMES[target - 1]
            cut = cut_borders(torch.from_numpy(mask)[None, None])[0]
            message = f"strike posture {target}: {name}"
            if cut:  # the fit flags a posture the picture cuts
                message += f" - step back: the picture cuts you at the {', '.join(cut)}"
            status.update(score=score, message=message)
            server.publish(
                _annotate(frame, templates[target - 1], score, status["message"]), status
            )
            if held >= max(1, round(hold_s * fps)):
                last = len(hold) - 1
                masks = np.stack([m for _, _, m in hold])
                used = held_frames(masks, last, 0, last, options.hold_frames, options.hold_iou)
                stack = torch.from_numpy(np.stack([hold[i][1] for i in used])).permute(0, 3, 1, 2)
                write_image(
                    out / "poses" / f"pose{target}.png",
                    median_frame(stack, list(range(len(used)))),
                )
                record[f"pose{target}"] = {
                    "name": name,
                    "frame": number,
                    "score": round(score, 4),
                    "combined_frames": [hold[i][0] for i in used],
                    "frame_cut": cut,
                }
                write_atomic(out / "capture.json", json.dumps({"postures": record}, indent=1))
                captured.append(target)
                target, held = target + 1, 0
                hold.clear()
        if realtime:
            time.sleep(1.0 / fps)
    video.release()
    return captured
