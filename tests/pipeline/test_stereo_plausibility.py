"""The stereo measurement rejects a view whose silhouette cannot be a person (a white frame
against a textured room) with the rule ``segmentation`` and the reason, before the rules run."""

from __future__ import annotations

import cv2
import numpy as np
import torch

from torchfit.camera import Camera, look_at
from torchfit.io.dataset import StereoInfo
from torchfit.pipeline.stereo import measure_stereo_pair

W, H = 80, 60


def _camera(x: float) -> Camera:
    R, t = look_at(torch.tensor([[3.0, x, 1.3]]), torch.tensor([[0.0, 0.0, 1.0]]))
    K = torch.tensor([[60.0, 0.0, 39.5], [0.0, 60.0, 29.5], [0.0, 0.0, 1.0]])
    return Camera(K=K, dist=torch.zeros(5), R=R[0], t=t[0], image_size=(W, H))


def test_a_white_view_fails_as_implausible(tmp_path) -> None:
    rng = np.random.default_rng(0)
    room = cv2.resize(rng.integers(40, 200, (6, 8, 3), dtype=np.uint8), (W, H))
    paths = {}
    for side in ("left", "right"):
        frames = []
        for i in range(5):
            path = tmp_path / side / f"bg{i}.png"
            path.parent.mkdir(parents=True, exist_ok=True)
            noise = rng.integers(-2, 3, room.shape)
            cv2.imwrite(str(path), np.clip(room.astype(int) + noise, 0, 255).astype(np.uint8))
            frames.append(path)
        paths[side] = frames
    white = tmp_path / "left.png"
    cv2.imwrite(str(white), np.full((H, W, 3), 255, np.uint8))
    stereo = StereoInfo(_camera(-0.2), _camera(0.2), paths["left"], paths["right"], white, white)
    result = measure_stereo_pair(stereo)
    assert result.status == "failed" and result.failed_rule == "segmentation"
    assert result.message.startswith("left view: segmentation implausible: it covers 100 %")
    assert result.measurements == {}
