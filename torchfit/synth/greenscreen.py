"""A green-screen studio for synthetic subjects (``SynthConfig.green_screen``): walls and floor
one green, nothing on them, the person dressed in no green (as one is told to dress in front
of a green screen: green clothes would be keyed out with the screen), and the screen's light
spilling onto the person's edge.

Spill: light bounced off the screen tints the person where the screen surrounds them; it is
strongest on the silhouette's edge and fades over ``SPILL_PX`` pixels inside it. Both use no
random numbers, so a subject drawn with and without the screen has the same body, postures
and camera.
"""

from __future__ import annotations

import cv2
import numpy as np

from torchfit.synth.room import Room

__all__ = ["SCREEN_GREEN", "SPILL_PX", "green_screen", "add_spill", "no_green"]

#: The screen's albedo (linear RGB), a typical chroma-key green.
SCREEN_GREEN = np.array([0.08, 0.42, 0.10])
#: How far into the person the spill reaches, pixels.
SPILL_PX = 4.0


def green_screen(room: Room) -> None:
    """Turn ``room`` into a green-screen studio in place: walls and floor of
    :data:`SCREEN_GREEN` (the floor a little darker), no furniture, pictures or posters."""
    room.wall_colour = SCREEN_GREEN.copy()
    room.floor_colours = np.stack([SCREEN_GREEN * 0.92, SCREEN_GREEN * 0.9])
    room.floor_kind = "tiles"
    room.plank_width = 1.0  # 3 m tiles: one seam-free sheet around the person
    room.boxes = []
    room.pictures = []
    room.posters = []
    room.pattern = None
    room.skirting = False


def add_spill(colour: np.ndarray, person: np.ndarray, strength: float) -> np.ndarray:
    """Tint the person's edge with the screen's light.

    Args:
        colour: (H, W, 3) linear RGB of the rendered view.
        person: (H, W) bool, where the body is visible.
        strength: the share of the screen's colour added on the edge itself (0: none).

    Returns:
        (H, W, 3) the tinted view (a copy).
    """
    if strength <= 0 or not person.any():
        return colour
    inside = cv2.distanceTransform(person.astype(np.uint8), cv2.DIST_L2, 5)
    weight = np.clip(1.0 - (inside - 1.0) / SPILL_PX, 0.0, 1.0) * person
    out = colour + strength * weight[..., None] * SCREEN_GREEN[None, None] * np.array([0, 1, 0])
    return np.clip(out, 0.0, 1.0)


def no_green(albedo: np.ndarray) -> np.ndarray:
    """The albedo (V, 3) with no green-dominant colour: where green exceeds both red and blue
    it is lowered to 0.8 of the larger of them (teal turns blue, green turns grey-brown)."""
    other = np.maximum(albedo[:, 0], albedo[:, 2])
    out = albedo.copy()
    out[:, 1] = np.where(albedo[:, 1] > other, 0.8 * other, albedo[:, 1])
    return out
