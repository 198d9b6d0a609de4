"""Where a tracked sequence's silhouettes come from (``segmentation.method``): its own
``masks/``, a chroma key, or background subtraction; and the errors of a sequence folder whose
parts do not fit together."""

import dataclasses
import json
import shutil

import cv2
import numpy as np
import pytest
import test_track
import torch
from test_track import SIZE, _three_frames, _write_sequence

from torchfit.errors import ConfigError, DataError, SegmentationError
from torchfit.image import fit_background, segment
from torchfit.io.camera import save_camera
from torchfit.io.images import list_images, load_frames
from torchfit.pipeline.sequence import SequenceSegmenter
from torchfit.pipeline.track import TrackConfig, load_sequence, track_sequences
from torchfit.track import TrackOptions

GREEN = (40, 190, 60)  # RGB of the screen
PERSON = (200, 150, 90)


# test_track's module fixtures, shared
model, camera = test_track.model, test_track.camera


def _config(**segmentation) -> TrackConfig:
    cfg = TrackConfig(track=TrackOptions(iterations=3, rounds=1))
    return dataclasses.replace(
        cfg, segmentation=dataclasses.replace(cfg.segmentation, **segmentation)
    )


def _ones(model):
    return torch.ones(model.num_segments, 3, dtype=torch.float64)


def _track(model, folder, out, cfg, start=None):
    seq = load_sequence(folder, method=cfg.segmentation.method)
    summary = track_sequences(model, _ones(model), [seq], [out], cfg, ahead="none", start=start)[0]
    return seq, summary, json.loads((out / "joints_world.json").read_text())["frames"]


def _write_masks(folder, cfg) -> None:
    """``masks/`` of a sequence folder: its own frames' background subtraction, as files."""
    size = load_sequence(folder).camera.image_size
    bg = fit_background(load_frames(list_images(folder / "background"), size)[0], cfg.segmentation)
    (folder / "masks").mkdir()
    for path in list_images(folder / "frames"):
        mask = segment(load_frames([path], size)[0], bg, cfg.segmentation).masks[0, 0]
        cv2.imwrite(str(folder / "masks" / path.name), mask.numpy().astype(np.uint8) * 255)


def test_a_sequence_with_its_own_masks_is_tracked_from_them(model, camera, tmp_path):
    """A sequence's ``masks/`` holding exactly what background subtraction makes of its frames
    tracks to byte-identical joints without ``background/``: ``auto`` takes the masks where the
    folder has them, and ``masks`` does too; ``background`` still subtracts."""
    folder, _ = _write_sequence(model, camera, tmp_path)
    cfg = _config(method="background")
    _, _, want = _track(model, folder, tmp_path / "subtracted", cfg)
    _write_masks(folder, cfg)
    shutil.rmtree(folder / "background")
    for method in ("auto", "masks"):
        seq, summary, got = _track(model, folder, tmp_path / method, _config(method=method))
        assert seq.method == "masks" and len(seq.masks) == 3
        assert got == want, method
        assert summary["status"]["ok"] == 3
    with pytest.raises(DataError, match=r"needs background/\*\.png for background subtraction"):
        load_sequence(folder, method="background")


def test_masks_that_do_not_fit_the_frames_are_named(model, camera, tmp_path):
    """Masks that do not number the frames, or one of another size than camera.yaml's (the
    first, found on reading the folder; a later one, found while tracking), are errors naming
    the folder or the file."""
    folder, _ = _write_sequence(model, camera, tmp_path)
    cfg = _config(method="masks")
    with pytest.raises(DataError, match="no masks/|image folder not found"):
        load_sequence(folder, method="masks")
    _write_masks(folder, _config(method="background"))
    (folder / "masks" / "000002.png").unlink()
    with pytest.raises(DataError, match=r"masks: 2 masks for 3 frames"):
        load_sequence(folder, method="auto")
    small = np.zeros((SIZE[1] // 2, SIZE[0] // 2), np.uint8)
    cv2.imwrite(str(folder / "masks" / "000002.png"), small)
    assert len(load_sequence(folder, max_frames=2).masks) == 2
    with pytest.raises(DataError, match=r"000002\.png: mask is 160x128 pixels, camera\.yaml"):
        track_sequences(
            model, _ones(model), [load_sequence(folder)], [tmp_path / "out"], cfg, ahead="none"
        )
    cv2.imwrite(str(folder / "masks" / "000000.png"), small)
    with pytest.raises(DataError, match=r"000000\.png: mask is 160x128 pixels"):
        load_sequence(folder)


def _write_green_sequence(model, camera, tmp_path, background: bool = True):
    """A three-frame sequence of the model's silhouettes before an unevenly lit green screen
    (sensor noise, and a darker band of screen beside the person as a shadow on it), the
    silhouettes drawn and the poses."""
    xs, masks = _three_frames(model, camera, "r_shoulder_abduct", 0.4, 0.15)
    folder = tmp_path / "green"
    (folder / "frames").mkdir(parents=True)
    save_camera(camera, folder / "camera.yaml")
    rng = np.random.default_rng(3)
    screen = np.empty((SIZE[1], SIZE[0], 3), np.float64)
    screen[:] = GREEN
    screen *= np.linspace(0.9, 1.05, SIZE[0])[None, :, None]

    def noisy(img):
        return np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)[..., ::-1]

    if background:
        (folder / "background").mkdir()
        for i in range(5):
            cv2.imwrite(str(folder / "background" / f"bg{i:02d}.png"), noisy(screen))
    for k, m in enumerate(masks):
        frame = screen.copy()
        ys, xs_ = np.nonzero(m)
        frame[ys.min() : ys.max(), xs_.max() : xs_.max() + 25] *= 0.6  # a shadow on the screen
        frame[m] = PERSON
        cv2.imwrite(str(folder / "frames" / f"{k:06d}.png"), noisy(frame))
    return folder, masks, xs


def _keyed(folder, cfg) -> np.ndarray:
    seq = load_sequence(folder, method=cfg.segmentation.method)
    return np.stack([m.numpy() for m in SequenceSegmenter(seq, cfg.segmentation).silhouettes()])


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_a_green_screen_sequence_is_tracked_by_its_chroma_key(model, camera, tmp_path):
    """``segmentation.method: chroma_key`` keys the frames against the screen of the background
    frames: the silhouettes are the drawn ones (the shadow on the screen stays screen), every
    frame is ``ok``, and from the true first pose the model's contour lies on them. Without
    background frames a key colour from the config does it; with neither, a config error."""
    folder, drawn, poses = _write_green_sequence(model, camera, tmp_path)
    cfg = _config(method="chroma_key")
    keyed = _keyed(folder, cfg)
    assert min(_iou(k, d) for k, d in zip(keyed, drawn, strict=True)) > 0.97
    seq, summary, got = _track(model, folder, tmp_path / "keyed", cfg)
    assert seq.method == "chroma_key" and summary["status"]["ok"] == 3, summary
    # from the first frame's true pose, the model's contour lies on the keyed silhouettes
    _track(model, folder, tmp_path / "from_truth", cfg, start=poses[:1])
    rms = _contour_rms(tmp_path / "from_truth")
    assert rms[0] < 1.0 and max(rms) < 2.0, rms  # px: the pose known, then tracked

    bare, drawn, _ = _write_green_sequence(model, camera, tmp_path / "bare", background=False)
    given = dataclasses.replace(cfg.segmentation.chroma_key, key=list(GREEN))
    given = dataclasses.replace(
        cfg, segmentation=dataclasses.replace(cfg.segmentation, chroma_key=given)
    )
    assert min(_iou(k, d) for k, d in zip(_keyed(bare, given), drawn, strict=True)) > 0.97
    assert _track(model, bare, tmp_path / "given", given)[1]["status"]["ok"] == 3
    with pytest.raises(ConfigError, match="chroma_key.key is not set"):
        _track(model, bare, tmp_path / "neither", cfg)


def _contour_rms(out) -> list[float]:
    return [float(r.split(",")[5]) for r in (out / "track.csv").read_text().split()[1:]]


def test_track_tool_exit_codes_for_masks_and_a_chroma_key(model, camera, tmp_path, capsys):
    """tools/track.py: the sequence's own masks, 0 (a model the fit judged ``poor_fit`` too, with
    a warning naming the fit's reasons; silhouettes the model cannot explain, with a warning on
    the sequence); masks of another size, 4 with the file named; a chroma key with neither a
    key colour nor background frames, 2 with the missing key named."""
    from scripts import load_script

    fitted = tmp_path / "fit"
    fitted.mkdir()
    scales = {s: [1.0, 1.0, 1.0] for s in model.template.segments}
    (fitted / "params.json").write_text(
        json.dumps({"template": "mpeg4_full", "segment_scales": scales})
    )
    folder, _ = _write_sequence(model, camera, tmp_path)
    _write_masks(folder, _config(method="background"))
    bare, _, _ = _write_green_sequence(model, camera, tmp_path / "bare", background=False)
    tool = load_script("tools/track.py")
    before = torch.get_num_threads()

    def run(sequence, out, *sets):
        argv = ["--config", "configs/track.yaml", "--model", str(fitted), "--sequence"]
        argv += [str(sequence), "--out", str(tmp_path / out), "--threads", "1"]
        return tool.main(argv + [a for s in sets for a in ("--set", s)])

    try:
        assert run(folder, "masks", "track.iterations=3", "track.rounds=1") == 0
        out = capsys.readouterr().out
        assert '"model_status": "ok"' in out
        drawn = json.loads(out[out.index("{") :])["sequences"][0]["median_confidence"]
        # silhouettes no pose explains (a block): tracked, with a warning on the sequence
        blocky = tmp_path / "blocky"
        shutil.copytree(folder, blocky)
        block = np.zeros((SIZE[1], SIZE[0]), np.uint8)
        block[40:220, 100:220] = 255
        for path in (blocky / "masks").iterdir():
            cv2.imwrite(str(path), block)
        assert run(blocky, "blocky", "track.iterations=3", "track.rounds=1") in (0, 1)
        out = capsys.readouterr()
        block = json.loads(out.out[out.out.index("{") :])["sequences"][0]["median_confidence"]
        assert block < min(drawn, 0.5) and f"blocky: median confidence {block:.2f}" in out.err
        doc = json.loads((fitted / "params.json").read_text())
        doc.update(status="poor_fit", message="pose1: the silhouette does not reach the floor")
        (fitted / "params.json").write_text(json.dumps(doc))
        assert run(folder, "doubtful", "track.iterations=3", "track.rounds=1") == 0
        out = capsys.readouterr()
        assert "is poor_fit (pose1: the silhouette does not reach the floor)" in out.err
        assert '"model_status": "poor_fit"' in out.out
        cv2.imwrite(str(folder / "masks" / "000001.png"), np.zeros((10, 10), np.uint8))
        capsys.readouterr()
        assert run(folder, "bad") == 4
        assert "000001.png: mask is 10x10 pixels" in capsys.readouterr().err
        assert run(bare, "neither", "segmentation.method=chroma_key") == 2
        assert "segmentation.chroma_key.key is not set" in capsys.readouterr().err
    finally:
        torch.set_num_threads(before)


def test_the_background_model_is_made_where_the_frames_are_read(model, camera, tmp_path):
    """Background subtraction's model is made on the first frame (in the reader process that
    segments the sequence, beside the other readers), the same model as made at once; too few
    background frames still fail when the segmenter is made, naming the sequence."""
    folder, _, _ = _write_green_sequence(model, camera, tmp_path)
    cfg = _config(method="background")
    seq = load_sequence(folder, method="background")
    segmenter = SequenceSegmenter(seq, cfg.segmentation)
    assert segmenter.model is None
    first = next(segmenter.silhouettes())
    assert segmenter.model is not None
    empty = load_frames(seq.background, seq.camera.image_size)[0]
    made = fit_background(empty, cfg.segmentation)
    assert torch.equal(segmenter.model.mean, made.mean)
    image = load_frames(seq.frames[:1], seq.camera.image_size)[0]
    assert torch.equal(first, segment(image, made, cfg.segmentation).masks[0, 0])
    strict = _config(method="background", min_background_frames=6).segmentation
    with pytest.raises(SegmentationError, match="green: 5 background frames, expected at least 6"):
        SequenceSegmenter(seq, strict)
