"""benchmarks/track_clips.py: the clips it makes and the table it writes (no tracking here)."""

import json

import pytest
from scripts import load_script

from torchfit.measurements import JOINT_NAMES


@pytest.fixture(scope="module")
def tool():
    return load_script("benchmarks/track_clips.py")


def test_the_clips_are_the_documented_ones(tool):
    dev, test = tool.CLIPS["dev"], tool.CLIPS["test"]
    assert len(dev) == 10 and len({c.name for c in dev}) == 10
    assert {c.motion for c in dev} == {"01_01.bvh"} and [c.motion for c in test] == ["11_01.amc"]
    assert (dev[0].start, dev[0].seed, dev[0].frames, dev[0].step) == (300, 11, 40, 4)
    assert (test[0].start, test[0].seed, test[0].frames) == (200, 19, 60)
    wide = tool.CLIPS["wide"]
    assert wide[:10] == dev and len({c.name for c in wide}) == 30
    # every clip's frames lie within the motion (01_01.bvh has 2,752 frames)
    assert max(c.start + (c.frames - 1) * c.step for c in wide) < 2752


def _eval(err: float, ok: int, uncertain: int) -> dict:
    return {
        "mean_joint_error_mm": err,
        "along_ray_mm": err * 0.8,
        "across_ray_mm": err * 0.4,
        "ms_per_frame": 100.0,
        "status": {"ok": ok, "uncertain": uncertain},
        "bridged_frames": uncertain // 2,
    }


def test_the_table_has_each_clip_then_the_mean_and_median(tool):
    text, rows = tool.summarise(
        {"a": _eval(60.0, 38, 2), "b": _eval(90.0, 30, 10), "c": _eval(150.0, 40, 0)}
    )
    assert rows[0][:2] == ["clip", "joint error mm"]
    assert rows[1] == ["a", "60.0", "48.0", "24.0", "100.0", "38", "0", "2", "1"]
    assert rows[4] == ["mean", "100.0", "80.0", "40.0", "100.0", "108", "0", "12", "6"]
    assert rows[5][:2] == ["median", "90.0"] and rows[5][5:] == ["", "", "", ""]
    assert text.splitlines()[2].startswith("| a | 60.0 |") and len(text.splitlines()) == 7
    # one clip: no summary rows
    _, alone = tool.summarise({"a": _eval(60.0, 38, 2)})
    assert len(alone) == 2


def test_true_silhouettes_are_a_sequence_of_its_own_masks(tool, tmp_path):
    """--true-silhouettes tracks a linked copy of the clip whose masks/ are its truth_masks/:
    a sequence folder whose silhouettes come from masks/ (segmentation.method auto or masks),
    made once."""
    import cv2
    import numpy as np

    from torchfit.io.camera import save_camera
    from torchfit.pipeline.sequence import load_sequence
    from torchfit.viz.preview import nominal_view

    seq = tmp_path / "clip" / "sequence"
    for sub in ("frames", "truth_masks", "background"):
        (seq / sub).mkdir(parents=True)
    save_camera(nominal_view(image_size=(64, 48)), seq / "camera.yaml")
    for k in range(2):
        cv2.imwrite(str(seq / "frames" / f"{k:06d}.png"), np.zeros((48, 64, 3), np.uint8))
        cv2.imwrite(str(seq / "truth_masks" / f"{k:06d}.png"), np.zeros((48, 64), np.uint8))
    joints = {n: [0.0, 0.0, 1.0] for n in JOINT_NAMES}
    (seq / "truth.json").write_text(json.dumps({"fps": 30, "joints_world": [joints, joints]}))
    folder = tool.with_true_silhouettes(seq)
    assert tool.with_true_silhouettes(seq) == folder == tmp_path / "clip" / "true_silhouettes"
    loaded = load_sequence(folder)
    assert loaded.method == "masks" and [p.name for p in loaded.masks] == [
        "000000.png",
        "000001.png",
    ]
    assert loaded.fps == 30 and not loaded.background
