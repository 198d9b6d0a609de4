"""benchmarks/repeatability.py: the noisy copy of a dataset and the change table (no fits)."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from scripts import load_script


@pytest.fixture(scope="module")
def tool():
    return load_script("benchmarks/repeatability.py")


def _subject(folder: Path, value: int) -> None:
    for sub in ("poses", "background", "stereo"):
        (folder / sub).mkdir(parents=True)
    (folder / "camera.yaml").write_text("image_size: [32, 24]\n")
    (folder / "truth.json").write_text("{}")
    image = np.full((24, 32, 3), value, np.uint8)
    cv2.imwrite(str(folder / "poses" / "pose1.png"), image)
    cv2.imwrite(str(folder / "background" / "bg0.png"), image)
    cv2.imwrite(str(folder / "stereo" / "left.png"), image)


def test_noisy_copy_perturbs_the_images_only_and_is_seeded(tool, tmp_path):
    _subject(tmp_path / "data" / "subject_000", 120)
    _subject(tmp_path / "data" / "subject_001", 80)
    (tmp_path / "data" / "notes").mkdir()  # not a subject: no camera.yaml
    first = tool.noisy_copy(tmp_path / "data", tmp_path / "a", 2.0, seed=3)
    again = tool.noisy_copy(tmp_path / "data", tmp_path / "b", 2.0, seed=3)
    assert sorted(p.name for p in first.iterdir()) == ["subject_000", "subject_001"]
    s = first / "subject_000"
    assert not (s / "stereo").exists()
    assert (s / "camera.yaml").read_text() == "image_size: [32, 24]\n"
    pose = cv2.imread(str(s / "poses" / "pose1.png")).astype(float)
    bg = cv2.imread(str(s / "background" / "bg0.png")).astype(float)
    for image in (pose, bg):
        assert 1.5 < (image - 120).std() < 2.5 and abs((image - 120).mean()) < 0.5
    same = cv2.imread(str(again / "subject_000" / "poses" / "pose1.png")).astype(float)
    assert np.array_equal(pose, same)


def test_changes_are_percent_of_the_first_fit_and_name_status_changes(tool):
    keys = tool.KEYS
    base = {
        "s0": {"status": "ok", **{k: "1.0" for k in keys}},
        "s1": {"status": "ok", **{k: "2.0" for k in keys}},
        "s2": {"status": "ok", **{k: "1.0" for k in keys}},
    }
    other = {
        "s0": {"status": "ok", **{k: "1.01" for k in keys}},
        "s1": {"status": "poor_fit", **{k: "1.9" for k in keys}},
        "s2": {"status": "failed", **{k: "" for k in keys}},
    }
    delta, moved = tool.changes(base, other)
    assert delta.shape == (2, len(keys))
    assert delta[0] == pytest.approx(1.0) and delta[1] == pytest.approx(5.0)
    assert moved == ["s1: ok -> poor_fit", "s2: ok -> failed"]
