"""Small six-posture subjects rendered from the template itself (no anny, no ../shared).

The person is the template body with known segment scales, shaded over a textured background
at a reduced image size, so pipeline tests run in seconds. Kept beside the tests that use it.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import torch

from torchfit.body.measure import measure_model
from torchfit.body.model import BodyModel
from torchfit.body.postures import POSTURES
from torchfit.image import SegmentationOptions, fit_background, segment
from torchfit.io.camera import save_camera
from torchfit.io.images import load_frames
from torchfit.viz.preview import nominal_view, render_pose_preview

SIZE = (360, 288)


def _background(rng: np.random.Generator, size: tuple[int, int] = SIZE) -> np.ndarray:
    w, h = size
    base = rng.integers(60, 200, size=(h // 24 + 1, w // 24 + 1, 3)).astype(np.uint8)
    image = cv2.resize(base, (w, h), interpolation=cv2.INTER_LINEAR)
    return cv2.GaussianBlur(image, (7, 7), 2.0)


def make_template_subject(
    folder: Path,
    model: BodyModel,
    scale: float = 1.0,
    seed: int = 0,
    azimuth_deg: float = 30.0,
    scales: torch.Tensor | None = None,
    image_size: tuple[int, int] = SIZE,
) -> dict:
    """Write one subject folder (design.md section 3 layout); returns its truth measurements.

    ``scales`` (1, S, 3), when given, are the body's segment scales (``scale`` is then unused).
    ``image_size`` (width, height): the focal length grows with the height, so the person
    fills the same share of the picture.
    """
    rng = np.random.default_rng(seed)
    focal = 450.0 * image_size[1] / SIZE[1]
    camera = nominal_view(distance=3.5, azimuth_deg=azimuth_deg, focal=focal, image_size=image_size)
    save_camera(camera, folder / "camera.yaml")
    bg = _background(rng, image_size)
    (folder / "background").mkdir(parents=True, exist_ok=True)
    (folder / "poses").mkdir(parents=True, exist_ok=True)
    noise = lambda img: np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)  # noqa: E731
    for i in range(5):
        cv2.imwrite(str(folder / "background" / f"bg{i:02d}.png"), noise(bg.astype(np.float64)))
    if scales is None:
        scales = torch.full((1, model.num_segments, 3), scale, dtype=model.dtype)
    for posture in POSTURES:
        image = render_pose_preview(model, camera, posture, scales, background=bg, outline=False)
        cv2.imwrite(
            str(folder / "poses" / f"pose{posture.index}.png"), noise(image.astype(np.float64))
        )
    truth = {k: float(v[0]) for k, v in measure_model(model, scales).items()}
    (folder / "truth.json").write_text(json.dumps(truth))
    return truth


def segment_subjects(subjects, **options) -> torch.Tensor:
    """(B, 6, H, W) silhouettes of loaded subjects by the colour test (``gamma`` 0.05, no shadow
    test) with the other :class:`~torchfit.image.SegmentationOptions` given."""
    cfg = SegmentationOptions(gamma=0.05, shadow_test=False, **options)
    masks = []
    for s in subjects:
        background, _ = load_frames(s.background)
        images, _ = load_frames(s.poses)
        masks.append(segment(images, fit_background(background, cfg), cfg).masks[:, 0])
    return torch.stack(masks)
