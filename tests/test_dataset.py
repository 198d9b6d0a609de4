"""Tests of torchfit.io.dataset with small temporary subject folders."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import pytest
import torch

from torchfit.camera import Camera, look_at
from torchfit.errors import DataError
from torchfit.io.camera import save_camera, save_stereo_cameras
from torchfit.io.dataset import load_dataset, load_subject, validate_subject, validate_truth


def _png(path: Path, width: int = 8, height: int = 6) -> None:
    """A tiny valid grey PNG written without an image library."""

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    raw = b"".join(b"\x00" + b"\x80" * width for _ in range(height))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )


def _camera() -> Camera:
    R, t = look_at(torch.tensor([[3.0, 0.0, 1.3]]), torch.tensor([[0.0, 0.0, 1.0]]))
    K = torch.tensor([[10.0, 0.0, 3.5], [0.0, 10.0, 2.5], [0.0, 0.0, 1.0]])
    return Camera(K=K, dist=torch.zeros(5), R=R[0], t=t[0], image_size=(8, 6))


def make_subject(root: Path, name: str, stereo: bool = False, truth: dict | None = None) -> Path:
    folder = root / name
    save_camera(_camera(), folder / "camera.yaml")
    for i in range(5):
        _png(folder / "background" / f"{i:02d}.png")
    for i in range(1, 7):
        _png(folder / "poses" / f"pose{i}.png")
    if truth is not None:
        (folder / "truth.json").write_text(json.dumps(truth))
    if stereo:
        save_stereo_cameras(_camera(), _camera(), folder / "stereo" / "cameras.yaml")
        for side in ("left", "right"):
            for i in range(5):
                _png(folder / "stereo" / "background" / side / f"{i:02d}.png")
            _png(folder / "stereo" / f"{side}.png")
    return folder


TRUTH = {
    "height_m": 1.78,
    "arm_span_m": 1.8,
    "joints_world": {"pose1": {"neck": [0.0, 0.0, 1.5]}, "stereo": {"l_knee": [0, 0.1, 0.5]}},
}


def test_valid_subject(tmp_path):
    folder = make_subject(tmp_path, "s01", stereo=True, truth=TRUTH)
    s = load_subject(folder)
    assert s.ok and s.status == "ok" and s.problems == [] and s.warnings == []
    assert s.name == "s01"
    assert [p.name for p in s.poses] == [f"pose{i}.png" for i in range(1, 7)]
    assert len(s.background) == 5
    assert s.camera is not None and s.camera.image_size == (8, 6)
    assert s.truth == TRUTH
    assert s.stereo is not None and s.stereo.left_image.name == "left.png"
    assert len(s.stereo.background_right) == 5
    assert validate_subject(folder) == []


def test_problems_name_the_file(tmp_path):
    folder = make_subject(tmp_path, "bad", truth={"height_m": -1, "shoe": 3})
    (folder / "poses" / "pose3.png").unlink()
    (folder / "background" / "00.png").unlink()
    _png(folder / "poses" / "pose5.png", width=9)
    problems = validate_subject(folder)
    text = "\n".join(problems)
    assert "pose3.png: missing posture image" in text
    assert "background: expected >= 5 background frames, found 4" in text
    assert "pose5.png: posture image is 9x6 pixels, camera.yaml image_size is 8x6" in text
    assert "truth.json: key 'height_m' expects a positive number" in text
    assert "truth.json: unknown key 'shoe'" in text
    s = load_subject(folder)
    assert not s.ok and s.truth is None
    with pytest.raises(DataError, match="subject 'bad' is invalid"):
        s.raise_if_invalid()


def test_bad_camera_and_json(tmp_path):
    folder = make_subject(tmp_path, "cam")
    (folder / "camera.yaml").write_text("image_size: [8, 6]\n")
    (folder / "truth.json").write_text("{not json")
    problems = validate_subject(folder)
    assert any("camera.yaml: missing key 'K'" in p for p in problems)
    assert any("truth.json: invalid JSON" in p for p in problems)


def test_bad_stereo_is_a_warning(tmp_path):
    folder = make_subject(tmp_path, "st", stereo=True)
    (folder / "stereo" / "right.png").unlink()
    s = load_subject(folder)
    assert s.ok and s.stereo is None
    assert any("right.png: missing stereo image" in w for w in s.warnings)


def test_validate_truth_joints():
    bad = {"joints_world": {"pose7": {}, "pose1": {"nose": [0, 0, 0], "neck": [0, 0]}}}
    problems = validate_truth(bad, "t.json")
    assert any("unknown capture 'joints_world.pose7'" in p for p in problems)
    assert any("unknown joint 'joints_world.pose1.nose'" in p for p in problems)
    assert any("'joints_world.pose1.neck' expects [x, y, z]" in p for p in problems)
    assert validate_truth([], "t.json") == ["t.json: expected a JSON object, got list"]


def test_load_dataset_folder_keeps_going(tmp_path):
    make_subject(tmp_path, "b")
    make_subject(tmp_path, "a")
    (tmp_path / "c").mkdir()  # an empty, bad subject
    subjects = load_dataset(tmp_path)
    assert [s.name for s in subjects] == ["a", "b", "c"]
    assert [s.ok for s in subjects] == [True, True, False]
    chosen = load_dataset(tmp_path, subjects=["b", "zz"])
    assert [s.name for s in chosen] == ["b", "zz"]
    assert "subject folder not found" in chosen[1].problems[0]


def test_a_subject_folder_given_as_the_dataset_is_named(tmp_path):
    make_subject(tmp_path, "alice")
    with pytest.raises(DataError, match=r"is a subject folder .*data.subjects=\[alice\]"):
        load_dataset(tmp_path / "alice")


def test_a_sequence_beside_the_subjects_is_named_as_one(tmp_path):
    """tools/make_sequence.py writes subject/ and sequence/ side by side: the sequence (frames/,
    no poses/) fails with what it is and how to leave it out, not six missing postures."""
    make_subject(tmp_path, "subject")
    (tmp_path / "sequence" / "frames").mkdir(parents=True)
    subjects = {s.name: s for s in load_dataset(tmp_path)}
    assert subjects["subject"].ok and not subjects["sequence"].ok
    (problem,) = subjects["sequence"].problems
    assert "a sequence (frames/, for tools/track.py), not a subject (poses/)" in problem
    assert "data.subjects" in problem


def test_load_dataset_manifest(tmp_path):
    data = tmp_path / "data"
    make_subject(data, "s1")
    make_subject(data, "s2")
    manifest = tmp_path / "list.txt"
    manifest.write_text("# subjects\ndata/s2\n\ndata/s1  # first\n")
    subjects = load_dataset(manifest)
    assert [s.name for s in subjects] == ["s2", "s1"]
    assert all(s.ok for s in subjects)
    with pytest.raises(DataError, match="dataset folder or manifest not found"):
        load_dataset(tmp_path / "missing")


def test_shipped_demo_dataset_is_valid():
    demo = Path(__file__).resolve().parents[1] / "data" / "demo"
    if not demo.is_dir():
        pytest.skip("data/demo is not in this checkout")
    subjects = load_dataset(demo)
    assert [s.name for s in subjects] == ["subject_000", "subject_001"]
    for s in subjects:
        assert s.ok, s.problems
        assert s.camera.image_size == (720, 576)
        assert 0.9 <= s.truth["arm_span_m"] / s.truth["height_m"] <= 1.1
        assert set(s.truth["joints_world"]) == {f"pose{i}" for i in range(1, 7)}
