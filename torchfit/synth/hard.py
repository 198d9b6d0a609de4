"""The hard rooms' conditions: wall shadows, furniture, textures, exposure, JPEG.

Each condition is switched by its own :class:`~torchfit.synth.options.SynthConfig` key and
draws its random numbers from its own stream (``default_rng([seed, index, k])``), never from
the subject's main stream: with every key off a subject is bit-identical to one made before
the hard rooms existed, and switching one condition changes only what it is about (same
body, postures, camera and room otherwise), which is what an ablation needs.

- ``wall_shadows``: the back wall 0.7-1.2 m behind the person, the light low (15-35 degrees)
  and 20-45 degrees to the side of the camera, and the body's shadow cast on every surface by
  a shadow map: it lands on the back wall and the furniture beside the arms and the head.
- ``furniture``: a bookshelf (rows of book spines), a cabinet and a door against the back
  wall, beside the person (they replace the standard room's boxes on that wall).
- ``textures``: patterned walls (stripes, checks or wallpaper) and posters.
- ``exposure_change``, ``white_balance``, ``exposure_drift``: the camera's gain changes
  between the background frames and each posture image (common and per channel), and drifts
  slowly over the capture.
- ``jpeg_quality``: every image goes through a JPEG encode/decode before it is written (the
  dataset's files stay PNG, design.md section 3).

World frame of design.md section 2, room frame ``(f, s, z)`` of :mod:`torchfit.synth.room`.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from torchfit.synth.options import SynthConfig
from torchfit.synth.room import Box, Light, Room
from torchfit.synth.texture import sample_pattern, sample_poster

__all__ = ["HardConditions"]

# one random stream per condition (the third entry of the seed sequence)
_LIGHT, _FURNITURE, _TEXTURES, _GAIN, _JPEG = 101, 102, 103, 104, 105


class HardConditions:
    """The hard-room conditions of one subject.

    Args:
        cfg: the generator options (which conditions are on).
        seed, index: the subject's seed and index (the streams derive from them).
        captures: the number of images of the main camera in capture order (background
            frames, then the postures): capture ``k`` is taken at time ``k / captures``.
    """

    def __init__(self, cfg: SynthConfig, seed: int, index: int, captures: int) -> None:
        self.cfg = cfg
        self.captures = captures
        self._rng = {
            k: np.random.default_rng([seed, index, k]) for k in (_LIGHT, _FURNITURE, _TEXTURES)
        }
        self._gain_rng = np.random.default_rng([seed, index, _GAIN])
        self._jpeg_rng = np.random.default_rng([seed, index, _JPEG])
        d = cfg.exposure_drift
        self._drift = self._gain_rng.uniform(-d, d, 3) if d > 0 else np.zeros(3)

    @property
    def all_surfaces(self) -> bool:
        """Whether the body's shadow is cast on every surface (a shadow map)."""
        return self.cfg.wall_shadows

    def scene(self, room: Room, light: Light) -> Light:
        """Apply the scene conditions to ``room`` (in place) and return the light to use."""
        if self.cfg.wall_shadows:
            rng = self._rng[_LIGHT]
            new_back = rng.uniform(0.7, 1.2)
            for box in room.boxes:  # the clutter against the back wall moves with it
                if math.isclose(box.lo[0], -room.back):
                    box.hi[0] += room.back - new_back
                    box.lo[0] = -new_back
            room.back = new_back
            az = room.azimuth + rng.choice([-1, 1]) * math.radians(rng.uniform(20, 45))
            el = math.radians(rng.uniform(15, 35))
            direction = np.array(
                [math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)]
            )
            light = Light(
                direction, ambient=rng.uniform(0.22, 0.35), diffuse=rng.uniform(0.65, 0.8)
            )
        if self.cfg.furniture:
            room.boxes = [b for b in room.boxes if not math.isclose(b.lo[0], -room.back)]
            room.boxes += _furniture(self._rng[_FURNITURE], room.back)
        if self.cfg.textures:
            rng = self._rng[_TEXTURES]
            room.pattern = sample_pattern(rng)
            room.pictures = []
            room.posters = [sample_poster(rng, (-2.4, 1.6)) for _ in range(rng.integers(2, 5))]
        return light

    def background_gain(self, k: int) -> np.ndarray:
        """(3,) gain factor of background frame ``k`` (the drift only)."""
        return 1 + self._drift * k / self.captures

    def posture_gain(self, k: int) -> np.ndarray:
        """(3,) gain factor of capture ``k``: exposure and white balance changes, drift."""
        rng, e, wb = self._gain_rng, self.cfg.exposure_change, self.cfg.white_balance
        exposure = 1 + (rng.uniform(-e, e) if e > 0 else 0.0)
        balance = 1 + (rng.uniform(-wb, wb, 3) if wb > 0 else np.zeros(3))
        return exposure * balance * (1 + self._drift * min(k, self.captures) / self.captures)

    @property
    def changes_gain(self) -> bool:
        """Whether any exposure condition is on."""
        cfg = self.cfg
        return cfg.exposure_change > 0 or cfg.white_balance > 0 or cfg.exposure_drift > 0

    def encode(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 RGB after a JPEG round trip (unchanged when JPEG is off)."""
        if not self.cfg.jpeg_quality:
            return rgb
        low, high = self.cfg.jpeg_quality
        quality = int(self._jpeg_rng.integers(low, high + 1))
        ok, data = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        return cv2.imdecode(data, cv2.IMREAD_COLOR)[..., ::-1]


def _furniture(rng: np.random.Generator, back: float) -> list[Box]:
    """A bookshelf on one side of the person, a cabinet and a door on the other, against the
    back wall at ``f = -back`` (room frame)."""
    side = rng.choice([-1, 1])
    boxes = []
    # bookshelf: inner edge 0.35-0.8 m beside the person
    inner = rng.uniform(0.35, 0.8)
    width, height = rng.uniform(0.8, 1.4), rng.uniform(1.7, 2.1)
    s_lo, s_hi = sorted((side * inner, side * (inner + width)))
    wood = rng.choice(np.array([[0.45, 0.3, 0.18], [0.7, 0.55, 0.38], [0.85, 0.85, 0.82]]))
    boxes.append(
        Box(
            np.array([-back, s_lo, 0.0]),
            np.array([-back + 0.32, s_hi, height]),
            wood * rng.uniform(0.9, 1.1),
            "books",
        )
    )
    # cabinet on the other side, then a door beyond it
    inner = rng.uniform(0.4, 0.9)
    width, height = rng.uniform(0.6, 1.0), rng.uniform(0.8, 1.15)
    s_lo, s_hi = sorted((-side * inner, -side * (inner + width)))
    boxes.append(
        Box(
            np.array([-back, s_lo, 0.0]),
            np.array([-back + 0.45, s_hi, height]),
            rng.uniform(0.2, 0.85, 3),
            "cabinet",
        )
    )
    start = inner + width + rng.uniform(0.15, 0.5)
    s_lo, s_hi = sorted((-side * start, -side * (start + 0.9)))
    paint = rng.choice(np.array([[0.9, 0.9, 0.88], [0.55, 0.38, 0.24], [0.3, 0.35, 0.45]]))
    boxes.append(
        Box(np.array([-back, s_lo, 0.0]), np.array([-back + 0.04, s_hi, 2.05]), paint, "door")
    )
    return boxes
