"""A corpus of bad subject folders, each beside the good one it is copied from.

``make_corpus(root, good)`` writes one folder per kind of bad input named in the issues
"Runs you can trust" and "Work in rooms it was not tuned in", and returns, per folder, a
regular expression that the subject's message in summary.csv must match. Kept beside the
tests that use it.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import yaml


def _copy(good: Path, root: Path, name: str) -> Path:
    folder = root / name
    shutil.copytree(good, folder)
    return folder


def _edit_camera(folder: Path, edit) -> None:
    path = folder / "camera.yaml"
    data = yaml.safe_load(path.read_text())
    edit(data)
    path.write_text(yaml.safe_dump(data))


def _write_png(path: Path, rgb: np.ndarray) -> None:
    import cv2

    cv2.imwrite(str(path), rgb[:, :, ::-1])


def _size(good: Path) -> tuple[int, int]:
    data = yaml.safe_load((good / "camera.yaml").read_text())
    return int(data["image_size"][0]), int(data["image_size"][1])


def make_corpus(root: Path, good: Path) -> dict[str, str]:
    """Bad subject folders under ``root`` made from the good subject ``good``.

    Returns:
        folder name -> regular expression for its message in summary.csv.
    """
    w, h = _size(good)
    expected: dict[str, str] = {}

    folder = _copy(good, root, "truncated_png")
    data = (folder / "poses" / "pose2.png").read_bytes()
    (folder / "poses" / "pose2.png").write_bytes(data[: len(data) // 3])
    expected[folder.name] = r"pose2\.png"

    folder = _copy(good, root, "corrupt_png")
    (folder / "poses" / "pose3.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00garbage" * 50)
    expected[folder.name] = r"pose3\.png"

    folder = _copy(good, root, "missing_posture")
    (folder / "poses" / "pose4.png").unlink()
    expected[folder.name] = r"pose4"

    folder = _copy(good, root, "wrong_size")
    _write_png(folder / "poses" / "pose5.png", np.full((h // 2, w // 2, 3), 128, np.uint8))
    expected[folder.name] = r"pose5\.png.*(size|\d+x\d+)"

    folder = _copy(good, root, "empty_background")
    for f in (folder / "background").iterdir():
        f.unlink()
    expected[folder.name] = r"background"

    folder = _copy(good, root, "nan_camera")
    _edit_camera(folder, lambda d: d["K"][0].__setitem__(0, float("nan")))
    expected[folder.name] = r"camera\.yaml.*(K|finite|NaN|nan)"

    folder = _copy(good, root, "non_rotation_camera")
    _edit_camera(folder, lambda d: d["R"][0].__setitem__(0, 2.0))
    expected[folder.name] = r"camera\.yaml.*(R|rotation)"

    folder = _copy(good, root, "camera_not_yaml")
    (folder / "camera.yaml").write_text("K: [1, 2\n  - : : {\n")
    expected[folder.name] = r"camera\.yaml"

    folder = _copy(good, root, "background_as_posture")
    first = sorted((folder / "background").iterdir())[0]
    shutil.copy(first, folder / "poses" / "pose6.png")
    expected[folder.name] = r"pose6"

    folder = _copy(good, root, "all_black_posture")
    _write_png(folder / "poses" / "pose4.png", np.zeros((h, w, 3), np.uint8))
    expected[folder.name] = r"pose4"

    folder = _copy(good, root, "all_white_posture")
    _write_png(folder / "poses" / "pose1.png", np.full((h, w, 3), 255, np.uint8))
    expected[folder.name] = r"pose1"

    return expected
