"""Acclaim motion capture (ASF skeleton + AMC motion), as the CMU database distributes it.

:func:`read_asf_amc` gives the world position of every bone's end per frame (file length
units, the file's axes: y up for CMU). The conventions are the Acclaim ones: a bone's
``axis`` (degrees, order ``XYZ``) gives its local frame ``C = Rz Ry Rx``; a frame's bone
rotation ``M`` (its ``dof`` values, missing ones zero) composes as ``Rz Ry Rx`` as well; the
bone's world rotation is ``L = L_parent C M C^-1`` and its end is its start plus
``length * L direction``. The root's start is its translation channels; its rotation is
``C_root M_root C_root^-1``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchfit.errors import DataError
from torchfit.io.bvh import euler_to_matrix

__all__ = ["AcclaimMotion", "read_asf_amc"]

_DOF = {"rx": 0, "ry": 1, "rz": 2}


@dataclass
class AcclaimMotion:
    """Bone end positions of an AMC motion.

    Attributes:
        names: bone names, ``root`` first (parents before children).
        parents: parent index per bone, -1 for the root.
        positions: (F, J, 3) world position of each bone's end (the root: its origin).
        length_unit: the ASF's ``:units length`` value.
    """

    names: list[str]
    parents: list[int]
    positions: np.ndarray
    length_unit: float


def _xyz(values: list[float]) -> np.ndarray:
    """``Rz Ry Rx`` of (rx, ry, rz) in degrees."""
    rx, ry, rz = (math.radians(v) for v in values)
    return euler_to_matrix([rz, ry, rx], "ZYX")


def _read_asf(path: Path) -> tuple[dict, dict[str, list[str]], float, np.ndarray]:
    text = [ln.split("#")[0].strip() for ln in path.read_text(errors="replace").splitlines()]
    bones: dict[str, dict] = {}
    children: dict[str, list[str]] = {}
    unit = 1.0
    root_axis = np.eye(3)
    section, bone = "", None
    for line in text:
        if not line:
            continue
        words = line.split()
        if line.startswith(":"):
            section = words[0][1:].lower()
            continue
        key = words[0].lower()
        if section == "units" and key == "length":
            unit = float(words[1])
        elif section == "root" and key == "orientation":
            root_axis = _xyz([float(v) for v in words[1:4]])
        elif section == "bonedata":
            if key == "begin":
                bone = {"dof": []}
            elif key == "end":
                bones[bone["name"]] = bone
                bone = None
            elif bone is not None and key == "name":
                bone["name"] = words[1]
            elif bone is not None and key == "direction":
                bone["direction"] = np.array([float(v) for v in words[1:4]])
            elif bone is not None and key == "length":
                bone["length"] = float(words[1])
            elif bone is not None and key == "axis":
                bone["C"] = _xyz([float(v) for v in words[1:4]])
            elif bone is not None and key == "dof":
                bone["dof"] = [w.lower() for w in words[1:]]
        elif section == "hierarchy" and key not in ("begin", "end"):
            children.setdefault(words[0], []).extend(words[1:])
    for name, b in bones.items():
        if "direction" not in b or "length" not in b or "C" not in b:
            raise DataError(f"{path}: bone {name!r} lacks direction, length or axis")
    if not bones or "root" not in children:
        raise DataError(f"{path}: no bonedata or no hierarchy from 'root'")
    return bones, children, unit, root_axis


def _read_amc(path: Path) -> list[dict[str, list[float]]]:
    frames: list[dict[str, list[float]]] = []
    for line in path.read_text(errors="replace").splitlines():
        line = line.split("#")[0].strip()
        if not line or line.startswith(":"):
            continue
        words = line.split()
        if len(words) == 1 and words[0].isdigit():
            frames.append({})
            continue
        if not frames:
            raise DataError(f"{path}: values before the first frame number")
        try:
            frames[-1][words[0]] = [float(v) for v in words[1:]]
        except ValueError:
            raise DataError(f"{path}: bad number in line {line!r}") from None
    if not frames:
        raise DataError(f"{path}: no frames")
    return frames


def read_asf_amc(asf: str | Path, amc: str | Path) -> AcclaimMotion:
    """Read an ASF skeleton and an AMC motion of it.

    Raises:
        DataError: a file is missing or malformed (the message names it).
    """
    asf, amc = Path(asf), Path(amc)
    for p in (asf, amc):
        if not p.is_file():
            raise DataError(f"motion capture file not found: {p}")
    bones, children, unit, root_c = _read_asf(asf)
    names, parents = ["root"], [-1]
    stack = [("root", 0)]
    while stack:
        name, idx = stack.pop(0)
        for child in children.get(name, []):
            if child not in bones:
                raise DataError(f"{asf}: hierarchy names unknown bone {child!r}")
            names.append(child)
            parents.append(idx)
            stack.append((child, len(names) - 1))
    frames = _read_amc(amc)
    pos = np.zeros((len(frames), len(names), 3))
    for f, values in enumerate(frames):
        if "root" not in values or len(values["root"]) < 6:
            raise DataError(f"{amc}: frame {f + 1} has no root translation and rotation")
        world = [np.eye(3)] * len(names)
        r = values["root"]
        world[0] = root_c @ _xyz(r[3:6]) @ root_c.T
        pos[f, 0] = r[:3]
        for j in range(1, len(names)):
            b = bones[names[j]]
            rot = [0.0, 0.0, 0.0]
            for k, dof in enumerate(b["dof"]):
                if dof in _DOF and k < len(values.get(names[j], [])):
                    rot[_DOF[dof]] = values[names[j]][k]
            world[j] = world[parents[j]] @ b["C"] @ _xyz(rot) @ b["C"].T
            pos[f, j] = pos[f, parents[j]] + b["length"] * (world[j] @ b["direction"])
    return AcclaimMotion(names=names, parents=parents, positions=pos, length_unit=unit)
