"""BVH motion files: read, write, and forward kinematics of the stored motion.

A :class:`Motion` is a skeleton (joints in depth-first order, each with a parent, an offset
in its parent's frame, its channels and an optional end site) plus one row of channel values
per frame. Rotation channels are in degrees and compose in the order they are listed: the
channels ``Zrotation Xrotation Yrotation`` give the joint's local rotation
``Rz(z) @ Rx(x) @ Ry(y)`` (the convention of Blender, MotionBuilder and the CMU files). A
joint's world transform is its parent's times ``[R | offset + translation]``.

The reader accepts ``#`` comment lines (the CMU files as distributed carry one).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchfit.errors import DataError, ShapeError
from torchfit.io.files import write_atomic

__all__ = ["Motion", "read_bvh", "write_bvh", "euler_to_matrix", "matrix_to_euler"]

_AXES = {"X": 0, "Y": 1, "Z": 2}
_ROTATIONS = ("Xrotation", "Yrotation", "Zrotation")
_POSITIONS = ("Xposition", "Yposition", "Zposition")


@dataclass
class Motion:
    """A BVH skeleton and its motion.

    Attributes:
        names: (J,) joint names, depth-first (parents before children).
        parents: (J,) parent index, -1 for the root.
        offsets: (J, 3) joint offset in its parent's frame (file units).
        channels: per joint, its channel names (``Xposition`` …, ``Zrotation`` …).
        end_sites: joint index -> (3,) offset of its end site.
        frame_time: seconds per frame.
        frames: (F, C) channel values, C = total number of channels, joints in order.
    """

    names: list[str]
    parents: list[int]
    offsets: np.ndarray
    channels: list[list[str]]
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)
    frame_time: float = 1 / 30
    frames: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    @property
    def num_frames(self) -> int:
        """F, the number of frames."""
        return int(self.frames.shape[0])

    def channel_slices(self) -> list[slice]:
        """Per joint, its columns of :attr:`frames`."""
        out, start = [], 0
        for ch in self.channels:
            out.append(slice(start, start + len(ch)))
            start += len(ch)
        return out

    def local_transforms(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(J, 3, 3) local rotations and (J, 3) local translations (offset + position
        channels) of one frame."""
        row = self.frames[frame]
        rots = np.tile(np.eye(3), (len(self.names), 1, 1))
        trans = self.offsets.astype(np.float64).copy()
        for j, sl in enumerate(self.channel_slices()):
            rot_names = [c for c in self.channels[j] if c in _ROTATIONS]
            values = row[sl]
            angles = [values[k] for k, c in enumerate(self.channels[j]) if c in _ROTATIONS]
            if rot_names:
                order = "".join(c[0] for c in rot_names)
                rots[j] = euler_to_matrix(np.radians(angles), order)
            for k, c in enumerate(self.channels[j]):
                if c in _POSITIONS:
                    trans[j, _AXES[c[0]]] += values[k]
        return rots, trans

    def world(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(J, 3) world joint positions and (J, 3, 3) world rotations of one frame."""
        rots, trans = self.local_transforms(frame)
        wr = np.zeros_like(rots)
        wp = np.zeros_like(trans)
        for j, p in enumerate(self.parents):
            if p < 0:
                wr[j], wp[j] = rots[j], trans[j]
            else:
                wr[j] = wr[p] @ rots[j]
                wp[j] = wp[p] + wr[p] @ trans[j]
        return wp, wr


def _axis_matrix(axis: int, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    if axis == 0:
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == 1:
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def euler_to_matrix(angles, order: str) -> np.ndarray:
    """(3, 3) rotation ``R_{order[0]}(a0) @ R_{order[1]}(a1) @ …`` (radians)."""
    out = np.eye(3)
    for axis, a in zip(order, angles, strict=True):
        out = out @ _axis_matrix(_AXES[axis], float(a))
    return out


def matrix_to_euler(rotation: np.ndarray, order: str) -> np.ndarray:
    """Angles (radians) with ``euler_to_matrix(angles, order) == rotation``.

    ``order`` is a permutation of ``XYZ``; the middle angle lies in [-90°, 90°].
    """
    from scipy.spatial.transform import Rotation  # scipy is a core dependency

    return Rotation.from_matrix(np.asarray(rotation, dtype=np.float64)).as_euler(order.upper())


# --------------------------------------------------------------------------------------------
# reading


def read_bvh(path: str | Path) -> Motion:
    """Read a BVH file.

    Raises:
        DataError: the file is missing or not valid BVH (the message names the problem).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"BVH file not found: {path}")
    lines = [ln.split("#")[0] for ln in path.read_text(errors="replace").splitlines()]
    tokens = [t for ln in lines for t in ln.split()]
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[list[str]] = []
    end_sites: dict[int, np.ndarray] = {}
    stack: list[int] = []
    i = 0

    def need(n: int) -> list[str]:
        nonlocal i
        if i + n > len(tokens):
            raise DataError(f"{path}: unexpected end of file in HIERARCHY")
        out = tokens[i : i + n]
        i += n
        return out

    try:
        if need(1)[0].upper() != "HIERARCHY":
            raise DataError(f"{path}: not a BVH file (no HIERARCHY)")
        pending_end = False
        while i < len(tokens) and tokens[i].upper() != "MOTION":
            tok = need(1)[0]
            up = tok.upper()
            if up in ("ROOT", "JOINT"):
                names.append(need(1)[0])
                parents.append(stack[-1] if stack else -1)
                offsets.append([0.0, 0.0, 0.0])
                channels.append([])
                stack.append(len(names) - 1)
            elif up == "END":
                need(1)  # "Site"
                pending_end = True
                stack.append(-2)
            elif up == "OFFSET":
                xyz = [float(v) for v in need(3)]
                if stack and stack[-1] == -2:
                    end_sites[stack[-2]] = np.array(xyz)
                elif stack:
                    offsets[stack[-1]] = xyz
            elif up == "CHANNELS":
                n = int(need(1)[0])
                channels[stack[-1]] = need(n)
            elif tok == "{":
                pass
            elif tok == "}":
                if not stack:
                    raise DataError(f"{path}: unbalanced braces in HIERARCHY")
                stack.pop()
                pending_end = False
            else:
                raise DataError(f"{path}: unexpected token {tok!r} in HIERARCHY")
        del pending_end
        if not names:
            raise DataError(f"{path}: no joints in HIERARCHY")
        need(1)  # MOTION
        if need(1)[0].rstrip(":").upper() != "FRAMES":
            raise DataError(f"{path}: expected 'Frames:' after MOTION")
        n_frames = int(need(1)[0])
        frame_word = need(2)
        if frame_word[0].upper() != "FRAME" or frame_word[1].rstrip(":").upper() != "TIME":
            raise DataError(f"{path}: expected 'Frame Time:'")
        frame_time = float(need(1)[0])
        n_channels = sum(len(c) for c in channels)
        values = np.array([float(v) for v in tokens[i:]], dtype=np.float64)
    except ValueError as exc:
        raise DataError(f"{path}: bad number in BVH ({exc})") from None
    if values.size < n_frames * n_channels:
        raise DataError(
            f"{path}: {n_frames} frames of {n_channels} channels announced, "
            f"{values.size} values found"
        )
    for j, ch in enumerate(channels):
        bad = [c for c in ch if c not in _ROTATIONS + _POSITIONS]
        if bad:
            raise DataError(f"{path}: joint {names[j]!r} has unknown channel {bad[0]!r}")
    return Motion(
        names=names,
        parents=parents,
        offsets=np.array(offsets, dtype=np.float64),
        channels=channels,
        end_sites=end_sites,
        frame_time=frame_time,
        frames=values[: n_frames * n_channels].reshape(n_frames, n_channels),
    )


# --------------------------------------------------------------------------------------------
# writing


def _fmt(values) -> str:
    return " ".join(f"{float(v):.6f}" for v in values)


def write_bvh(path: str | Path, motion: Motion) -> Path:
    """Write ``motion`` as a BVH file (atomically); returns the path.

    Raises:
        ShapeError: the frames do not match the channels.
        OutputError: the file cannot be written.
    """
    n_channels = sum(len(c) for c in motion.channels)
    frames = np.atleast_2d(np.asarray(motion.frames, dtype=np.float64))
    if frames.shape[1] != n_channels:
        raise ShapeError(f"frames: expected {n_channels} channels, got {frames.shape[1]}")
    children: dict[int, list[int]] = {j: [] for j in range(len(motion.names))}
    for j, p in enumerate(motion.parents):
        if p >= 0:
            children[p].append(j)
    out = ["HIERARCHY"]

    def emit(j: int, depth: int) -> None:
        pad = "\t" * depth
        word = "ROOT" if motion.parents[j] < 0 else "JOINT"
        out.append(f"{pad}{word} {motion.names[j]}")
        out.append(f"{pad}{{")
        out.append(f"{pad}\tOFFSET {_fmt(motion.offsets[j])}")
        ch = motion.channels[j]
        out.append(f"{pad}\tCHANNELS {len(ch)} {' '.join(ch)}".rstrip())
        for c in children[j]:
            emit(c, depth + 1)
        if not children[j]:
            end = motion.end_sites.get(j, np.zeros(3))
            out.append(f"{pad}\tEnd Site")
            out.append(f"{pad}\t{{")
            out.append(f"{pad}\t\tOFFSET {_fmt(end)}")
            out.append(f"{pad}\t}}")
        out.append(f"{pad}}}")

    roots = [j for j, p in enumerate(motion.parents) if p < 0]
    if len(roots) != 1:
        raise ShapeError(f"a BVH skeleton needs exactly one root, got {len(roots)}")
    order: list[int] = []
    children_first = dict(children)

    def visit(j: int) -> None:
        order.append(j)
        for c in children_first[j]:
            visit(c)

    visit(roots[0])
    if order != list(range(len(motion.names))):
        raise ShapeError("BVH joints must be listed depth-first (each subtree contiguous)")
    emit(roots[0], 0)
    out.append("MOTION")
    out.append(f"Frames: {frames.shape[0]}")
    out.append(f"Frame Time: {motion.frame_time:.8f}")
    out.extend(_fmt(row) for row in frames)
    return write_atomic(path, "\n".join(out) + "\n")
