"""What a subject folder's ``truth.json`` and ``subject.yaml`` may hold, and their checks."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

from torchfit.errors import yaml_problem
from torchfit.measurements import JOINT_NAMES, MEASUREMENT_KEYS

__all__ = [
    "N_POSES",
    "CAPTURE_NAMES",
    "FACT_KEYS",
    "SEXES",
    "HEIGHT_RANGE_M",
    "WEIGHT_RANGE_KG",
    "is_position",
    "validate_truth",
    "validate_facts",
    "load_facts",
]

#: Number of postures (design.md section 4).
N_POSES = 6
#: Keys of the optional ``subject.yaml`` (facts known about the subject).
FACT_KEYS: tuple[str, ...] = ("height_m", "weight_kg", "sex")
#: The values of ``subject.yaml``'s ``sex``.
SEXES: tuple[str, ...] = ("female", "male")
#: The heights (metres) and weights (kg) ``subject.yaml`` may give.
HEIGHT_RANGE_M: tuple[float, float] = (1.0, 2.5)
WEIGHT_RANGE_KG: tuple[float, float] = (20.0, 300.0)
#: Capture names of ``truth.json`` ``joints_world``.
CAPTURE_NAMES: tuple[str, ...] = tuple(f"pose{i}" for i in range(1, N_POSES + 1)) + ("stereo",)


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def is_position(value: Any) -> bool:
    """Whether ``value`` is a joint position as the truth files hold it: ``[x, y, z]``, three
    finite numbers (metres)."""
    return isinstance(value, list) and len(value) == 3 and all(_is_number(v) for v in value)


def validate_truth(data: Any, source: str = "truth.json") -> list[str]:
    """Problems of a parsed ``truth.json`` (empty when valid).

    Valid: a mapping whose keys are measurement keys (positive finite numbers, metres) and
    optionally ``joints_world`` (capture name -> joint name -> three finite numbers). Every key
    may be missing.
    """
    if not isinstance(data, dict):
        return [f"{source}: expected a JSON object, got {type(data).__name__}"]
    problems = []
    for key, value in data.items():
        if key == "joints_world":
            problems += _validate_joints_world(value, source)
        elif key in MEASUREMENT_KEYS:
            if not _is_number(value) or value <= 0:
                problems.append(
                    f"{source}: key '{key}' expects a positive number of metres, got {value!r}"
                )
        else:
            problems.append(
                f"{source}: unknown key '{key}' (valid keys: "
                f"{', '.join(MEASUREMENT_KEYS)}, joints_world)"
            )
    return problems


def _validate_joints_world(value: Any, source: str) -> list[str]:
    if not isinstance(value, dict):
        return [f"{source}: key 'joints_world' expects an object, got {type(value).__name__}"]
    problems = []
    for capture, joints in value.items():
        where = f"joints_world.{capture}"
        if capture not in CAPTURE_NAMES:
            problems.append(
                f"{source}: unknown capture '{where}' (valid: {', '.join(CAPTURE_NAMES)})"
            )
            continue
        if not isinstance(joints, dict):
            problems.append(f"{source}: key '{where}' expects an object of joint positions")
            continue
        for name, xyz in joints.items():
            if name not in JOINT_NAMES:
                problems.append(
                    f"{source}: unknown joint '{where}.{name}' (valid: {', '.join(JOINT_NAMES)})"
                )
            elif not is_position(xyz):
                problems.append(
                    f"{source}: key '{where}.{name}' expects [x, y, z] in metres, got {xyz!r}"
                )
    return problems


# --------------------------------------------------------------------------------------------
# subject.yaml


def validate_facts(data: Any, source: str = "subject.yaml") -> list[str]:
    """Problems of a parsed ``subject.yaml`` (empty when valid).

    Valid: a mapping with any of ``height_m`` (metres, within :data:`HEIGHT_RANGE_M`),
    ``weight_kg`` (within the range of an adult) and ``sex`` (``female`` or ``male``).
    """
    if not isinstance(data, dict):
        return [f"{source}: expected a mapping of facts, got {type(data).__name__}"]
    problems = []
    ranges = {"height_m": (HEIGHT_RANGE_M, "m"), "weight_kg": (WEIGHT_RANGE_KG, "kg")}
    for key, value in data.items():
        if key in ranges:
            (lo, hi), unit = ranges[key]
            if not _is_number(value) or not lo <= value <= hi:
                problems.append(
                    f"{source}: {key} must be a number from {lo:g} to {hi:g} {unit}, got {value!r}"
                )
        elif key == "sex":
            if value not in SEXES:
                problems.append(f"{source}: sex must be 'female' or 'male', got {value!r}")
        else:
            problems.append(f"{source}: unknown key {key!r} (valid keys: {', '.join(FACT_KEYS)})")
    return problems


def load_facts(path: Path, problems: list[str]) -> dict:
    """The facts of a ``subject.yaml`` (empty, with the reasons added to ``problems``, when
    it is not valid)."""
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        problems.append(f"{path}: invalid YAML: {yaml_problem(exc)}")
        return {}
    found = validate_facts({} if data is None else data, str(path))
    problems.extend(found)
    return {} if found else {k: data[k] for k in FACT_KEYS if k in data}
