"""Tracking: the per-frame pose LM on rendered silhouettes of the template, the tracker's
recovery after a corrupted frame, and batching."""

import math

import numpy as np
import pytest
import torch

from torchfit.body.model import BodyModel
from torchfit.camera import project_points
from torchfit.errors import ConfigError, DataError
from torchfit.fit.person import person_data_from_masks
from torchfit.track import PoseLayout, TrackOptions, solve_frame, track
from torchfit.viz.preview import nominal_view
from torchfit.viz.raster import render_silhouette

SIZE = (320, 256)
LIMBS = (
    "l_shoulder_abduct",
    "r_shoulder_abduct",
    "l_elbow_flexion",
    "r_elbow_flexion",
    "l_hip_flexion",
    "r_knee_flexion",
)


@pytest.fixture(scope="module")
def model():
    return BodyModel("mpeg4_full")


@pytest.fixture(scope="module")
def camera():
    return nominal_view(distance=3.5, azimuth_deg=0.0, focal=450.0, image_size=SIZE)


def _facing(camera) -> float:
    from torchfit.camera import camera_centre

    c = camera_centre(camera.R, camera.t)[0]
    return float(torch.atan2(c[1], c[0]))


def _pose(model, layout, camera, angles: dict[str, float], shift=(0.0, 0.0), yaw=0.0):
    x = torch.zeros(layout.num_params, dtype=torch.float64)
    x[0], x[1] = shift
    x[5] = _facing(camera) + yaw
    for name, v in angles.items():
        x[6 + model.dof_index(name)] = v
    with torch.no_grad():
        t, r, q = PoseLayout.split(x[None])
        low = model(model.zeros(1)["scales"], q, t, r).vertices[..., 2].min()
    x[2] = -low
    return x


def _masks(model, camera, x: torch.Tensor) -> torch.Tensor:
    scales = torch.ones(x.shape[0], model.num_segments, 3, dtype=torch.float64)
    t, r, q = PoseLayout.split(x)
    with torch.no_grad():
        pix = project_points(model(scales, q, t, r).vertices, camera)
    faces = model.faces.numpy()
    return torch.stack(
        [torch.from_numpy(render_silhouette(p.numpy(), faces, camera.image_size) > 0) for p in pix]
    )


def _joint_error_mm(model, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    scales = torch.ones(a.shape[0], model.num_segments, 3, dtype=torch.float64)
    with torch.no_grad():
        ja = model.joint_positions(model(scales, a[:, 6:], a[:, :3], a[:, 3:6]))
        jb = model.joint_positions(model(scales, b[:, 6:], b[:, :3], b[:, 3:6]))
    names = [n for n in model.template.joints]  # the measurement joints
    return 1000 * torch.stack([(ja[n] - jb[n]).norm(dim=-1) for n in names], 1).mean(1)


def test_frame_lm_recovers_a_pose_from_a_silhouette(model, camera):
    opts = TrackOptions(iterations=10, rounds=3, floor_weight=0.0)
    layout = PoseLayout(model, opts)
    angles = [
        {"l_shoulder_abduct": 0.9, "r_shoulder_abduct": 0.5, "l_elbow_flexion": 0.4},
        {
            "l_shoulder_abduct": 0.3,
            "r_shoulder_abduct": 1.1,
            "l_hip_flexion": 0.3,
            "r_knee_flexion": 0.4,
        },
    ]
    truth = torch.stack([_pose(model, layout, camera, a) for a in angles])
    cams = camera[[0, 0]]
    person = person_data_from_masks(_masks(model, cams, truth)[:, None], cams)
    g = torch.Generator().manual_seed(3)
    start = truth.clone()
    for name in LIMBS:
        start[:, 6 + model.dof_index(name)] += 0.2 * torch.randn(
            2, generator=g, dtype=torch.float64
        )
    start[:, :2] += 0.04
    start = layout.clip(start)
    scales = torch.ones(2, model.num_segments, 3, dtype=torch.float64)
    res = solve_frame(model, scales, person, layout, start, start, opts)
    before = _joint_error_mm(model, start, truth)
    after = _joint_error_mm(model, res.x, truth)
    # the silhouette is explained (contour within 2 px) and the joints move towards the truth;
    # what the one view cannot tell (twists, depth) stays near the start and its prediction
    assert (res.contour_rms < 2.0).all(), res.contour_rms
    assert (after < 0.8 * before).all(), (before, after)
    # rows are independent: the second row alone gives the same pose
    alone = solve_frame(
        model,
        scales[1:],
        person_data_from_masks(_masks(model, cams[[1]], truth[1:])[:, None], cams[[1]]),
        layout,
        start[1:],
        start[1:],
        opts,
    )
    torch.testing.assert_close(alone.x, res.x[1:], atol=1e-6, rtol=0)


def test_tracker_recovers_after_a_corrupted_frame(model, camera):
    # the recovery alone: constant-velocity prediction, no twist prior (the template sequence
    # has no model mismatch for them to absorb; tests/test_track_priors.py tests them)
    opts = TrackOptions(
        iterations=6, rounds=2, floor_weight=0.0, velocity_damping=1.0, twist_weight=0.0
    )
    layout = PoseLayout(model, opts)
    n = 12
    xs = torch.stack(
        [
            _pose(
                model,
                layout,
                camera,
                {
                    "l_shoulder_abduct": 0.3 + 0.6 * math.sin(k / 4),
                    "r_shoulder_abduct": 0.2 + 0.6 * k / n,
                    "l_hip_abduct": 0.2 * k / n,
                },
                shift=(0.0, 0.02 * k),
            )
            for k in range(n)
        ]
    )
    masks = _masks(model, camera[[0] * n], xs)
    # frame 5: a wrong silhouette (the person shifted by 60 px, as a segmentation failure)
    masks[5] = torch.roll(masks[5], 60, dims=1)
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    recs = track(model, scales, camera, (m[None] for m in masks), xs[:1], opts)[0]
    status = [r.status for r in recs]
    assert status[5] != "ok", status
    assert recs[5].confidence < recs[4].confidence
    err = _joint_error_mm(model, torch.stack([r.x for r in recs]), xs)
    print("joint error per frame (mm):", err)
    assert err[:5].max() < 60, err
    assert err[5] > 2 * err[4], err  # the bad frame is off ...
    # ... and the tracker is back within a few frames of it, with no frame lost afterwards
    assert err[8:].max() < 60, err
    assert all(s == "ok" for s in status[8:]), status


@pytest.mark.parametrize("every", [1, 4])
def test_a_lost_stretch_is_solved_again_now_and_then_and_left(model, camera, every, monkeypatch):
    """Frames whose silhouette is wrong for a stretch (the person shifted by 60 px in frames
    3-12): with ``recover_every`` the stretch's first ``every - 1`` frames and then every
    ``every``-th are solved again from the last good frame, the others once (1: all of them).
    Once the silhouettes are right again the tracker is back within ``every`` frames."""
    import torchfit.track.tracker as tracker

    opts = TrackOptions(
        iterations=4, rounds=2, floor_weight=0.0, twist_weight=0.0, recover_every=every
    )
    layout = PoseLayout(model, opts)
    n = 20
    xs = torch.stack(
        [
            _pose(model, layout, camera, {"l_shoulder_abduct": 0.3 + 0.4 * math.sin(k / 5)})
            for k in range(n)
        ]
    )
    masks = _masks(model, camera[[0] * n], xs)
    for k in range(3, 13):
        masks[k] = torch.roll(masks[k], 60, dims=1)
    solves = []
    solve = tracker.solve_frame
    monkeypatch.setattr(
        tracker, "solve_frame", lambda *a, **k: solves.append(a[5]) or solve(*a, **k)
    )
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    recs = track(model, scales, camera, (m[None] for m in masks), xs[:1], opts)[0]
    status = [r.status for r in recs]
    assert all(s == "uncertain" for s in status[3:13]), status
    # the stretch lasts until a re-solve from the last good frame fits again
    back = status.index("recovered")
    assert 13 <= back < 13 + every and set(status[3:back]) == {"uncertain"}, status
    # one solve a frame; on the stretch's frames solved again one more, of two rows: from the
    # last good frame and from the frame's own pose with the arms raised
    again = [p for p in range(back - 3 + 1) if p < every - 1 or p % every == 0]
    assert len(solves) == n + len(again), (status, len(solves))
    assert sorted({len(p) for p in solves}) == [1, 2]
    assert sum(len(p) == 2 for p in solves) == len(again)
    if every > 1:
        assert len(again) < back - 3  # not every frame of the stretch
    err = _joint_error_mm(model, torch.stack([r.x for r in recs]), xs)
    assert all(s == "ok" for s in status[back + 1 :]), status
    assert err[back:].max() < 60, err


def _three_frames(model, camera, dof: str, first: float, step: float):
    """Three poses turning ``dof`` by ``step`` from ``first`` (radians), and their (3, H, W)
    silhouettes as a bool array."""
    layout = PoseLayout(model, TrackOptions())
    xs = torch.stack([_pose(model, layout, camera, {dof: first + step * k}) for k in range(3)])
    return xs, _masks(model, camera[[0] * 3], xs).numpy()


def _empty_sequence(folder, camera, background: np.ndarray):
    """A sequence folder with ``camera.yaml``, five copies of the BGR image ``background`` as
    its empty scene, and an empty ``frames/``."""
    import cv2

    from torchfit.io.camera import save_camera

    (folder / "background").mkdir(parents=True)
    (folder / "frames").mkdir()
    save_camera(camera, folder / "camera.yaml")
    for i in range(5):
        cv2.imwrite(str(folder / "background" / f"bg{i:02d}.png"), background)
    return folder


def _write_sequence(model, camera, tmp_path, video: bool = False):
    """A three-frame sequence folder (the model's own silhouettes on a flat background), and
    the same frames as a lossless video when ``video`` (None if OpenCV cannot write one)."""
    import cv2

    _, masks = _three_frames(model, camera, "l_shoulder_abduct", 0.3, 0.1)
    rng = np.random.default_rng(0)
    bg = (60 + rng.integers(0, 3, (SIZE[1], SIZE[0], 3))).astype(np.uint8)
    folder = _empty_sequence(tmp_path / "seq", camera, bg)
    path = tmp_path / "clip.avi"
    fourcc = cv2.VideoWriter_fourcc(*"FFV1")
    writer = cv2.VideoWriter(str(path), fourcc, 25, SIZE) if video else None
    for k, m in enumerate(masks):
        frame = bg.copy()
        frame[m] = (200, 150, 90)
        cv2.imwrite(str(folder / "frames" / f"{k:06d}.png"), frame)
        if writer is not None:
            writer.write(frame)
    if writer is None:
        return folder, None
    writer.release()
    return folder, path if path.stat().st_size else None


@pytest.mark.parametrize("arms", [0.0, 45.0])
def test_an_arm_raised_out_of_the_solves_reach_is_found_by_the_recovery(model, camera, arms):
    """The left arm raised from hanging to 75° between two frames: the solve leaves the model's
    arm beside the trunk, where the silhouette's raised arm does not pull it, and the re-solve
    from the last good frame starts there too. Solved again from its own pose with an arm
    raised sideways (``recover_arms_deg``), the frame is ``recovered`` and the arm followed;
    without (0), it stays ``uncertain``."""
    opts = TrackOptions(recover_arms_deg=arms)
    layout = PoseLayout(model, opts)
    hanging = {"l_shoulder_abduct": 0.05, "r_shoulder_abduct": 0.05}
    down = _pose(model, layout, camera, hanging)
    up = _pose(model, layout, camera, {**hanging, "l_shoulder_abduct": 1.3})
    xs = torch.stack([down] * 3 + [up] * 4)
    masks = _masks(model, camera[[0] * 7], xs)
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    recs = track(model, scales, camera, [m[None] for m in masks], down[None], opts)[0]
    status = [r.status for r in recs]
    raised = float(recs[-1].x[6 + model.dof_index("l_shoulder_abduct")])
    assert status[:3] == ["ok"] * 3, status
    if arms:
        assert status[3:] == ["recovered", "ok", "ok", "ok"], status
        assert abs(raised - 1.3) < 0.25 and recs[-1].contour_rms < 1.5, (raised, recs[-1])
    else:
        assert status[3:] == ["uncertain"] * 4, status
        assert raised < 0.5


def test_a_first_frame_far_off_is_uncertain(model, camera):
    """With no good frame before it, a frame is judged on its own: a first silhouette the model
    cannot explain (the person shifted 60 px from where the start puts them, as a start gone
    wrong) is ``uncertain``, not ``ok``; one it explains is ``ok``."""
    from torchfit.track.options import LOST_CONFIDENCE

    # without the re-solve with raised arms, which brings this model, shifted whole, to 11 px
    # (within the first frame's limit): the status is what is checked here
    opts = TrackOptions(iterations=1, rounds=1, recover_arms_deg=0.0)
    layout = PoseLayout(model, opts)
    x = _pose(model, layout, camera, {"l_shoulder_abduct": 0.3, "r_shoulder_abduct": 0.3})[None]
    mask = _masks(model, camera, x)  # (1, H, W)
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    good = track(model, scales, camera, [mask], x, opts)[0][0]
    assert good.status == "ok" and good.contour_rms < LOST_CONFIDENCE * opts.confidence_px
    off = torch.roll(mask, 60, dims=2)
    lost = track(model, scales, camera, [off], x, opts)[0][0]
    assert lost.contour_rms > LOST_CONFIDENCE * opts.confidence_px, lost.contour_rms
    assert lost.status == "uncertain", lost


def test_a_video_tracks_like_its_frames(model, camera, tmp_path):
    """The same frames as PNG files and as a (lossless) video give the same track."""
    from torchfit.pipeline.track import TrackConfig, load_sequence, track_sequences

    folder, video = _write_sequence(model, camera, tmp_path, video=True)
    if video is None:
        pytest.skip("this OpenCV build cannot write FFV1 video")
    cfg = TrackConfig(track=TrackOptions(iterations=3, rounds=1))
    scales = torch.ones(model.num_segments, 3, dtype=torch.float64)
    outs = [tmp_path / "png", tmp_path / "video"]
    seqs = [load_sequence(folder), load_sequence(folder, video=video)]
    assert seqs[1].num_frames == 3
    track_sequences(model, scales, seqs[:1], outs[:1], cfg)
    track_sequences(model, scales, seqs[1:], outs[1:], cfg)
    a = (outs[0] / "track.csv").read_text().splitlines()
    b = (outs[1] / "track.csv").read_text().splitlines()
    assert len(a) == len(b) == 4
    assert [r.split(",")[5] for r in a] == [r.split(",")[5] for r in b]  # same contour RMS


def test_frames_read_ahead_in_a_thread_or_a_process_track_alike(model, camera, tmp_path):
    """Reading and segmenting the next frames in a thread, a second process or in line gives
    byte-identical joints; an unknown choice is an error."""
    from torchfit.pipeline.track import TrackConfig, load_sequence, track_sequences

    folder, _ = _write_sequence(model, camera, tmp_path)
    cfg = TrackConfig(track=TrackOptions(iterations=3, rounds=1))
    scales = torch.ones(model.num_segments, 3, dtype=torch.float64)
    joints = {}
    for ahead in ("thread", "process", "none"):
        out = tmp_path / ahead
        track_sequences(model, scales, [load_sequence(folder)], [out], cfg, ahead=ahead)
        joints[ahead] = (out / "joints_world.json").read_bytes()
    assert joints["process"] == joints["thread"] == joints["none"]
    with pytest.raises(ValueError, match="ahead: expected"):
        track_sequences(model, scales, [load_sequence(folder)], [tmp_path / "x"], cfg, ahead="gpu")


def test_sequences_read_by_several_processes_track_as_by_one(model, camera, tmp_path):
    """Three sequences (one a frame shorter) read and segmented by one process, by two groups
    of them in processes of their own beside the tracker, by three from a reader process and
    by three (four asked) beside a reader thread: byte-identical joints for every sequence."""
    import shutil

    from torchfit.pipeline.track import TrackConfig, load_sequence, track_sequences

    folder, _ = _write_sequence(model, camera, tmp_path)
    short = tmp_path / "short"
    shutil.copytree(folder, short)
    (short / "frames" / "000002.png").unlink()
    cfg = TrackConfig(track=TrackOptions(iterations=3, rounds=1))
    scales = torch.ones(model.num_segments, 3, dtype=torch.float64)
    joints = {}
    for readers, ahead in ((1, "none"), (2, "none"), (3, "process"), (4, "thread")):
        seqs = [load_sequence(f) for f in (folder, short, folder)]
        outs = [tmp_path / f"r{readers}" / str(i) for i in range(3)]
        track_sequences(model, scales, seqs, outs, cfg, ahead=ahead, readers=readers)
        joints[readers] = [(o / "joints_world.json").read_bytes() for o in outs]
    assert joints[1] == joints[2] == joints[3] == joints[4]
    assert joints[1][0] == joints[1][2] and joints[1][0] != joints[1][1]  # the short one


def test_different_sequences_tracked_together_track_as_alone(model, camera, tmp_path):
    """Two sequences of different motions (the left arm raised, the right elbow bent) tracked
    together with the shipped options, the first frames' starts included: each one's joints
    and motion are byte-identical to it tracked alone (every problem's damped system is
    factored and solved as it is alone: torchfit.solver.normal.cholesky_each)."""
    import cv2

    from torchfit.pipeline.track import TrackConfig, load_sequence, track_sequences

    arm, _ = _write_sequence(model, camera, tmp_path)
    rng = np.random.default_rng(1)
    bg = (60 + rng.integers(0, 3, (SIZE[1], SIZE[0], 3))).astype(np.uint8)
    elbow = _empty_sequence(tmp_path / "elbow", camera, bg)
    for k, m in enumerate(_three_frames(model, camera, "r_elbow_flexion", 0.4, 0.25)[1]):
        frame = bg.copy()
        frame[m] = (90, 160, 210)
        cv2.imwrite(str(elbow / "frames" / f"{k:06d}.png"), frame)
    cfg = TrackConfig()
    scales = torch.ones(model.num_segments, 3, dtype=torch.float64)
    folders = [arm, elbow]
    together = [tmp_path / "together" / str(i) for i in range(2)]
    track_sequences(model, scales, [load_sequence(f) for f in folders], together, cfg, ahead="none")
    for i, folder in enumerate(folders):
        alone = tmp_path / "alone" / str(i)
        track_sequences(model, scales, [load_sequence(folder)], [alone], cfg, ahead="none")
        for name in ("joints_world.json", "motion.bvh"):
            assert (together[i] / name).read_bytes() == (alone / name).read_bytes(), (i, name)
    assert (together[0] / "joints_world.json").read_bytes() != (
        together[1] / "joints_world.json"
    ).read_bytes()


def test_overlays_are_frames_and_a_video_that_reads_back(model, camera, tmp_path, monkeypatch):
    """``overlays=True`` writes one PNG a frame and ``overlay.avi`` with the same frames
    (Motion JPEG: the same images up to the codec's loss), and no partial file is left. The
    silhouettes they draw are those the frames were tracked to, handed over by the reader: the
    same PNGs whether it ran in line or in a second process."""
    from torchfit.io.images import load_frames
    from torchfit.io.video import read_video, video_frame_count
    from torchfit.pipeline.track import TrackConfig, load_sequence, track_sequences

    folder, _ = _write_sequence(model, camera, tmp_path)
    cfg = TrackConfig(track=TrackOptions(iterations=2, rounds=1))
    scales = torch.ones(model.num_segments, 3, dtype=torch.float64)
    out = tmp_path / "out"
    track_sequences(model, scales, [load_sequence(folder)], [out], cfg, ahead="none", overlays=True)
    pngs = sorted((out / "overlay").glob("*.png"))
    assert len(pngs) == 3 and video_frame_count(out / "overlay.avi") == 3
    assert not list(out.glob(".*part*"))
    png = load_frames(pngs, SIZE)[0]
    video = torch.cat(list(read_video(out / "overlay.avi", SIZE)))
    assert (video - png).abs().mean() < 0.02  # JPEG's loss, in [0, 1]
    other = tmp_path / "process"
    track_sequences(
        model, scales, [load_sequence(folder)], [other], cfg, ahead="process", overlays=True
    )
    assert [p.read_bytes() for p in pngs] == [
        p.read_bytes() for p in sorted((other / "overlay").glob("*.png"))
    ]
    # each frame's person is its segmentation
    import torchfit.viz.overlay as overlay
    from torchfit.image import fit_background, segment

    drawn = []
    draw = overlay.fit_overlay
    monkeypatch.setattr(overlay, "fit_overlay", lambda *a: drawn.append(a[1]) or draw(*a))
    track_sequences(model, scales, [load_sequence(folder)], [tmp_path / "spy"], cfg, overlays=True)
    seq = load_sequence(folder)
    background = fit_background(load_frames(seq.background, SIZE)[0], cfg.segmentation)
    people = [segment(i, background, cfg.segmentation).masks[0, 0] for i in seq.images()]
    assert len(drawn) == 3 and all(d.any() for d in drawn)
    assert all(np.array_equal(d, p.numpy()) for d, p in zip(drawn, people, strict=True))


def test_a_video_writer_refuses_a_frame_of_another_size_and_leaves_no_file(tmp_path):
    from torchfit.errors import OutputError
    from torchfit.io.video import VideoWriter

    path = tmp_path / "v.avi"
    with pytest.raises(OutputError, match="frame of 32x16"):
        with VideoWriter(path, 25.0) as video:
            video.write(np.zeros((24, 32, 3), np.uint8))
            video.write(np.zeros((16, 32, 3), np.uint8))
    assert not path.exists() and not list(tmp_path.iterdir())


def test_a_known_start_is_tracked_from_instead_of_the_first_frame_s_own(
    model, camera, tmp_path, monkeypatch
):
    """``track_sequences(start=...)`` tracks the first frame from the caller's pose rows: the
    silhouettes' own start is not solved, the first frame is the solve from the rows given
    (here the rendered pose, which it keeps within 2-3 px), and rows of the wrong shape are
    an error that names the shape expected."""
    import torchfit.pipeline.track as pipeline
    from torchfit.pipeline.track import TrackConfig, load_sequence

    folder, _ = _write_sequence(model, camera, tmp_path)
    cfg = TrackConfig(track=TrackOptions(iterations=3, rounds=1))
    scales = torch.ones(model.num_segments, 3, dtype=torch.float64)
    layout = PoseLayout(model, cfg.track)
    true_first = _pose(model, layout, camera, {"l_shoulder_abduct": 0.3})

    def no_start(*args, **kwargs):
        raise AssertionError("start_poses was called")

    monkeypatch.setattr(pipeline, "start_poses", no_start)
    out = tmp_path / "known"
    pipeline.track_sequences(
        model, scales, [load_sequence(folder)], [out], cfg, ahead="none", start=true_first[None]
    )
    rows = (out / "track.csv").read_text().splitlines()
    assert len(rows) == 4 and float(rows[1].split(",")[5]) < 1.5  # contour RMS, px
    import json

    got = json.loads((out / "joints_world.json").read_text())["frames"][0]
    with torch.no_grad():
        want = model.joint_positions(
            model(scales[None], true_first[None, 6:], true_first[None, :3], true_first[None, 3:6])
        )
    err = [1000 * np.linalg.norm(np.array(got[n]) - want[n][0].numpy()) for n in got]
    assert np.mean(err) < 20.0 and max(err) < 30.0, err  # 1 px is about 8 mm here
    with pytest.raises(ValueError, match=rf"start: expected \(1, {layout.num_params}\)"):
        pipeline.track_sequences(
            model, scales, [load_sequence(folder)], [tmp_path / "x"], cfg, start=true_first
        )


def _pixels(model, scales, camera, x, vertex_index):
    """(B, K, 2) pixels of the posed vertices ``vertex_index`` (None: all) of pose rows ``x``."""
    t, r, q = PoseLayout.split(x)
    return project_points(model(scales, q, t, r, vertex_index=vertex_index).vertices, camera)


@pytest.mark.parametrize("depth", [0.0, 50.0])
def test_analytic_frame_jacobian_matches_central_differences(model, camera, depth):
    from torchfit.fit.model_contour import EdgeSampler, select_contour
    from torchfit.track.residual import _FrameResidual

    opts = TrackOptions(temporal_depth=depth)  # with and without the limbs' depth pull
    layout = PoseLayout(model, opts)
    truth = _pose(model, layout, camera, {"l_shoulder_abduct": 0.8, "r_knee_flexion": 0.5})[None]
    person = person_data_from_masks(_masks(model, camera, truth)[:, None], camera, stride=3)
    g = torch.Generator().manual_seed(7)
    x = layout.clip(truth + 0.03 * torch.randn(truth.shape, generator=g, dtype=torch.float64))
    x[:, 3:6] += 0.2  # a root rotation well away from zero
    scales = 1 + 0.1 * torch.rand(1, model.num_segments, 3, generator=g, dtype=torch.float64)
    sampler = EdgeSampler(model.faces, opts.samples_per_edge)
    pix = _pixels(model, scales, camera, x, None)
    sel = select_contour(sampler, pix, person.contours[0], person.valid[0], SIZE, 1.0)
    problem = _FrameResidual(model, scales, person, layout, truth, sampler, sel)
    rows = torch.arange(1)
    jac, r0 = problem.analytic_jacobian(x, rows)
    r, mask = problem(x, rows)
    torch.testing.assert_close(r0, r, atol=1e-12, rtol=0)
    # one-sided differences on both sides: e_P's nearest point on an edge and the bilinear
    # distance map have kinks, where the derivative is one side's (a central difference
    # straddling one is neither)
    h = 1e-7
    ahead, behind = [], []
    for i in range(x.shape[1]):
        step = torch.zeros_like(x)
        step[:, i] = h
        ahead.append((problem(x + step, rows)[0] - r) / h)
        behind.append((r - problem(x - step, rows)[0]) / h)
    keep = mask[..., None].expand_as(jac)
    err = torch.minimum(
        (jac - torch.stack(ahead, -1)).abs(), (jac - torch.stack(behind, -1)).abs()
    )[keep]
    assert jac[keep].abs().max() > 1.0  # the contour terms do depend on the pose
    assert err.max() < 1e-4 * (1 + jac[keep].abs().max()), err.max()


def test_a_handed_over_pass_gives_the_residual_and_jacobian_of_a_fresh_one(model, camera):
    """The contour choice's kinematics pass of every vertex, handed to the solve's residual
    (:meth:`_FrameResidual.start_from`), gives bit for bit the residual and the Jacobian that
    posing the residual's own vertices gives; at any other pose the residual poses anew."""
    from torchfit.fit.model_contour import EdgeSampler, select_contour
    from torchfit.track.residual import _FrameResidual

    opts = TrackOptions()
    layout = PoseLayout(model, opts)
    truth = _pose(model, layout, camera, {"l_shoulder_abduct": 0.8, "r_knee_flexion": 0.5})[None]
    person = person_data_from_masks(_masks(model, camera, truth)[:, None], camera, stride=3)
    g = torch.Generator().manual_seed(5)
    x = layout.clip(truth + 0.03 * torch.randn(truth.shape, generator=g, dtype=torch.float64))
    scales = 1 + 0.1 * torch.rand(1, model.num_segments, 3, generator=g, dtype=torch.float64)
    sampler = EdgeSampler(model.faces, opts.samples_per_edge)
    t, r, q = PoseLayout.split(x)
    every = torch.arange(model.template.vertices.shape[0])
    whole = model.pose_pass(scales, q, t, r, every)
    pix = project_points(whole[2].vertices, camera)
    sel = select_contour(sampler, pix, person.contours[0], person.valid[0], SIZE, 1.0)
    rows = torch.arange(1)

    def problem():
        return _FrameResidual(model, scales, person, layout, truth, sampler, sel)

    fresh, handed = problem(), problem()
    handed.start_from(x, rows, whole)
    assert torch.equal(handed(x, rows)[0], fresh(x, rows)[0])
    jac_h, r_h = handed.analytic_jacobian(x, rows)
    jac_f, r_f = fresh.analytic_jacobian(x, rows)
    assert torch.equal(jac_h, jac_f) and torch.equal(r_h, r_f)
    # elsewhere the hand-over is not used
    y = layout.clip(x + 0.05)
    again = problem()
    again.start_from(x, rows, whole)
    assert torch.equal(again(y, rows)[0], fresh(y, rows)[0])
    assert not torch.equal(fresh(y, rows)[0], fresh(x, rows)[0])
    # handed over for the analytic Jacobian: the first residual there is made with the
    # Jacobian (the same numbers), which the solver's Jacobian call then takes as made
    ahead = problem()
    ahead.start_from(x, rows, whole, jacobian=True)
    r_a, mask_a = ahead(x, rows)
    assert torch.equal(r_a, fresh(x, rows)[0]) and torch.equal(mask_a, fresh(x, rows)[1])
    made = ahead._ahead[2]
    jac_a, r_ja = ahead.analytic_jacobian(x, rows)
    assert jac_a is made[0] and r_ja is made[1]  # handed back, not made again
    assert torch.equal(jac_a, jac_f) and torch.equal(r_ja, r_f)
    assert torch.equal(ahead(y, rows)[0], fresh(y, rows)[0])
    assert ahead.analytic_jacobian(x, rows)[0] is not made[0]  # once only


def _one_frame(model, camera, opts, offset):
    """One frame of the left arm raised: the layout, the true pose row, the person data, a
    start ``truth + offset(truth)`` within the limits, unit scales, the edge sampler and the
    model-contour choice at the start."""
    from torchfit.fit.model_contour import EdgeSampler, select_contour

    layout = PoseLayout(model, opts)
    truth = _pose(model, layout, camera, {"l_shoulder_abduct": 0.8})[None]
    person = person_data_from_masks(_masks(model, camera, truth)[:, None], camera, stride=3)
    x = layout.clip(truth + offset(truth))
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    sampler = EdgeSampler(model.faces, opts.samples_per_edge)
    pix = _pixels(model, scales, camera, x, None)
    sel = select_contour(sampler, pix, person.contours[0], person.valid[0], SIZE, 1.0)
    return layout, truth, person, x, scales, sampler, sel


def test_the_frame_jacobian_reuses_the_residuals_pass_only_at_its_point(model, camera, monkeypatch):
    """After the residual at x, the Jacobian at x takes that evaluation's kinematics pass;
    at any other point it makes its own. Either way it is the Jacobian a fresh problem gives,
    bit for bit."""
    from torchfit.track.residual import _FrameResidual

    opts = TrackOptions()
    g = torch.Generator().manual_seed(3)
    layout, truth, person, x, scales, sampler, sel = _one_frame(
        model, camera, opts, lambda t: 0.03 * torch.randn(t.shape, generator=g, dtype=t.dtype)
    )
    other = layout.clip(x + 0.01)
    rows = torch.arange(1)

    def problem():
        return _FrameResidual(model, scales, person, layout, truth, sampler, sel)

    passes = []
    real = model.pose_pass
    monkeypatch.setattr(model, "pose_pass", lambda *a: passes.append(1) or real(*a))
    used = problem()
    used(x, rows)
    for at, made in ((x, 0), (other, 1)):  # the residual's point, then another
        before = len(passes)
        jac, r0 = used.analytic_jacobian(at, rows)
        assert len(passes) - before == made
        fresh_jac, fresh_r0 = problem().analytic_jacobian(at, rows)
        assert torch.equal(jac, fresh_jac) and torch.equal(r0, fresh_r0)


def test_a_solve_uses_its_own_options_weights(model, camera):
    # the layout is made once from the tracker's options; a start or a restart solves with
    # other temporal weights, and those are the ones that count
    layout = PoseLayout(model, TrackOptions())
    truth = _pose(model, layout, camera, {"l_shoulder_abduct": 0.8})[None]
    person = person_data_from_masks(_masks(model, camera, truth)[:, None], camera, stride=3)
    start = truth.clone()
    start[0, 6 + model.dof_index("l_shoulder_abduct")] = 0.4
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    held = TrackOptions(
        iterations=4, rounds=1, temporal_joints=1e6, temporal_rotation=1e6, temporal_translation=1e6
    )
    free = TrackOptions(iterations=8, rounds=2)
    stuck = solve_frame(model, scales, person, layout, start, start, held)
    moved = solve_frame(model, scales, person, layout, start, start, free)
    assert (stuck.x - start).abs().max() < 1e-4
    k = 6 + model.dof_index("l_shoulder_abduct")
    assert abs(float(moved.x[0, k]) - 0.8) < abs(float(start[0, k]) - 0.8) / 2


def test_track_tool_threads(tmp_path, capsys):
    """tools/track.py leaves one core to the reader that reads and segments the next frames
    (torch takes one thread fewer than the cores, at least 1), and rejects --threads 0 with
    exit code 2 (as --readers 0 and --frames 0 or below)."""
    from scripts import load_script

    from torchfit.pipeline.runtime import cpu_count

    tool = load_script("tools/track.py")
    base = ["--config", "configs/track.yaml", "--sequence", str(tmp_path), "--out", str(tmp_path)]
    with pytest.raises(SystemExit) as exc:
        tool.main([*base, "--model", str(tmp_path), "--threads", "0"])
    assert exc.value.code == 2
    assert "--threads must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        tool.main([*base, "--model", str(tmp_path), "--readers", "0"])
    assert exc.value.code == 2
    assert "--readers must be >= 1" in capsys.readouterr().err
    for frames in ("0", "-2"):
        with pytest.raises(SystemExit) as exc:
            tool.main([*base, "--model", str(tmp_path), "--frames", frames])
        assert exc.value.code == 2
        assert "--frames must be >= 1" in capsys.readouterr().err
    before = torch.get_num_threads()
    try:
        assert tool.main([*base, "--model", str(tmp_path / "no_fit")]) == 4  # no params.json
        assert torch.get_num_threads() == max(1, cpu_count() - 1)
    finally:
        torch.set_num_threads(before)


def _unit_model(model, folder):
    """A fitted subject folder of the template at unit scales (its params.json only)."""
    import json

    folder.mkdir()
    scales = {s: [1.0, 1.0, 1.0] for s in model.template.segments}
    (folder / "params.json").write_text(
        json.dumps({"template": "mpeg4_full", "segment_scales": scales})
    )
    return folder


def test_track_tool_names_an_unreadable_frame_with_exit_code_4(model, camera, tmp_path, capsys):
    """A frame that cannot be read, found while tracking (in the reader process), stops the
    run with the file named and exit code 4, as an unreadable sequence does."""

    from scripts import load_script

    folder, _ = _write_sequence(model, camera, tmp_path)
    (folder / "frames" / "000001.png").write_bytes(b"not a png")
    fitted = _unit_model(model, tmp_path / "fit")
    tool = load_script("tools/track.py")
    before = torch.get_num_threads()
    try:
        argv = ["--config", "configs/track.yaml", "--model", str(fitted), "--sequence"]
        code = tool.main([*argv, str(folder), "--out", str(tmp_path / "out"), "--threads", "1"])
    finally:
        torch.set_num_threads(before)
    assert code == 4
    assert "000001.png" in capsys.readouterr().err


def test_a_sequence_with_an_unreadable_frame_costs_the_others_nothing(
    model, camera, tmp_path, capsys
):
    """Two sequences tracked together, the first with a frame that cannot be read: it is
    named and left out (exit code 4), and the second's outputs are those it has alone."""
    from scripts import load_script

    bad, _ = _write_sequence(model, camera, tmp_path / "a")
    good, _ = _write_sequence(model, camera, tmp_path / "b")
    (bad / "frames" / "000001.png").write_bytes(b"not a png")
    fitted = _unit_model(model, tmp_path / "fit")
    tool = load_script("tools/track.py")
    argv = ["--config", "configs/track.yaml", "--model", str(fitted), "--threads", "1"]
    before = torch.get_num_threads()
    try:
        both = [*argv, "--sequence", str(bad), "--sequence", str(good), "--ahead", "process"]
        code = tool.main([*both, "--out", str(tmp_path / "both")])
        err = capsys.readouterr().err
        alone = tool.main([*argv, "--sequence", str(good), "--out", str(tmp_path / "alone")])
    finally:
        torch.set_num_threads(before)
    assert code == 4
    assert "000001.png" in err and str(bad) in err
    assert not (tmp_path / "both" / "00_seq").exists()
    assert alone == 0
    for name in ("joints_world.json", "motion.bvh"):
        written = (tmp_path / "both" / "01_seq" / name).read_bytes()
        assert written == (tmp_path / "alone" / name).read_bytes(), name


def test_a_frame_missing_from_the_numbering_is_named(model, camera, tmp_path):
    """frames/000000.png, 000002.png: the missing 000001 is named when the sequence is loaded
    (tracked on, every later frame would meet another frame's truth)."""
    from torchfit.pipeline.sequence import load_sequence

    folder, _ = _write_sequence(model, camera, tmp_path)
    (folder / "frames" / "000001.png").unlink()
    with pytest.raises(DataError, match="frame 000001 is missing"):
        load_sequence(folder)


@pytest.mark.parametrize(
    ("truth", "message"),
    [
        ("{not json", "cannot read the truth"),
        ('{"fps": "fast", "joints_world": []}', "key 'fps' expects a positive number"),
        ('{"joints_world": {"back": [0, 0, 1]}}', "key 'joints_world' expects a list of frames"),
        ('{"joints_world": [{}]}', "1 truth frames for 3 frames to track"),
        ("FRAMES_WITHOUT_AN_ANKLE", r"joints_world\[2\] expects \[x, y, z\] .* l_ankle"),
    ],
)
def test_a_malformed_truth_is_named_before_tracking(model, camera, tmp_path, truth, message):
    """truth.json is checked when the sequence is loaded (the frames not yet tracked): the
    error names the file and the key."""
    import json

    from torchfit.measurements import JOINT_NAMES
    from torchfit.pipeline.sequence import load_sequence

    folder, _ = _write_sequence(model, camera, tmp_path)
    if truth == "FRAMES_WITHOUT_AN_ANKLE":
        joints = {n: [0.0, 0.0, 1.0] for n in JOINT_NAMES}
        frames = [joints, joints, {k: v for k, v in joints.items() if k != "l_ankle"}]
        truth = json.dumps({"fps": 25, "joints_world": frames})
    (folder / "truth.json").write_text(truth)
    with pytest.raises(DataError, match=message) as info:
        load_sequence(folder)
    assert str(folder / "truth.json") in str(info.value)


def test_joint_errors_split_along_and_across_the_camera_ray():
    """eval.json's split: a joint moved along the camera's ray through it, or across it."""
    from torchfit.camera import Camera, look_at
    from torchfit.measurements import JOINT_NAMES
    from torchfit.pipeline.track import joint_errors

    centre = torch.tensor([[0.5, -4.0, 1.5]], dtype=torch.float64)
    R, t = look_at(centre, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    K = torch.tensor([[800.0, 0.0, 360.0], [0.0, 800.0, 288.0], [0.0, 0.0, 1.0]])
    camera = Camera(K=K, dist=torch.zeros(5), R=R[0], t=t[0], image_size=(720, 576))
    rng = np.random.default_rng(3)
    truth = [{n: list(rng.uniform(-0.5, 0.5, 3) + [0, 0, 1]) for n in JOINT_NAMES}]
    ray = {n: np.subtract(truth[0][n], centre[0].numpy()) for n in JOINT_NAMES}
    ray = {n: v / np.linalg.norm(v) for n, v in ray.items()}
    away = [{n: list(np.add(truth[0][n], 0.02 * ray[n])) for n in JOINT_NAMES}]
    e = joint_errors(away, truth, camera)
    assert e["mean_joint_error_mm"] == pytest.approx(20.0)
    assert e["along_ray_mm"] == pytest.approx(20.0) and e["along_ray_signed_mm"] == pytest.approx(
        20.0
    )
    assert e["across_ray_mm"] == pytest.approx(0.0, abs=1e-9)
    side = {n: np.cross(ray[n], [0.0, 0.0, 1.0]) for n in JOINT_NAMES}
    side = {n: v / np.linalg.norm(v) for n, v in side.items()}
    across = [{n: list(np.add(truth[0][n], 0.03 * side[n])) for n in JOINT_NAMES}]
    e = joint_errors(across, truth, camera)
    assert e["across_ray_mm"] == pytest.approx(30.0) and e["along_ray_mm"] == pytest.approx(
        0.0, abs=1e-9
    )
    assert "along_ray_mm" not in joint_errors(across, truth)


def test_the_contour_terms_are_in_reference_pixels_and_the_rest_is_not(model, camera):
    """``reference_px_per_m``: a row's e_P and e_M (and their Jacobian rows) are its image
    pixels times its ``scale``, every other term is untouched; a frame solved at twice the
    camera's resolution reports its contour RMS in its own pixels and reads the limits in
    reference pixels (``FrameResult.reference_rms``)."""
    from torchfit.fit.model_contour import select_contour
    from torchfit.fit.options import pixels_per_metre
    from torchfit.track.residual import _FrameResidual

    opts = TrackOptions()
    layout, truth, person, x, scales, sampler, sel = _one_frame(
        model, camera, opts, lambda t: torch.full_like(t, 0.02)
    )
    rows = torch.arange(1)
    args = (model, scales, person, layout, truth, sampler, sel, None)
    plain = _FrameResidual(*args)
    scaled = _FrameResidual(*args, torch.tensor([2.5], dtype=torch.float64))
    jac_p, r_p = plain.analytic_jacobian(x, rows)
    jac_s, r_s = scaled.analytic_jacobian(x, rows)
    image = torch.zeros(r_p.shape[1], dtype=torch.bool)
    image[: person.contours[0].shape[1] + sel.sample_valid.shape[1]] = True
    assert float(r_p[0, image].abs().sum()) > 0 and float(r_p[0, ~image].abs().sum()) > 0
    torch.testing.assert_close(r_s[:, image], 2.5 * r_p[:, image])
    torch.testing.assert_close(jac_s[:, image], 2.5 * jac_p[:, image])
    torch.testing.assert_close(r_s[:, ~image], r_p[:, ~image])
    torch.testing.assert_close(jac_s[:, ~image], jac_p[:, ~image])

    # the same pose through a camera of twice the resolution: its contour errors are twice
    # as many of its pixels, and as many reference pixels
    from torchfit.fit.options import image_scale

    sharp = nominal_view(distance=3.5, azimuth_deg=0.0, focal=900.0, image_size=(640, 512))
    reference = float(pixels_per_metre(camera)[0])

    def rms(cam, size, ref):
        seen = person_data_from_masks(_masks(model, cam, truth)[:, None], cam, stride=3)
        at = _pixels(model, scales, cam, x, None)
        chosen = select_contour(sampler, at, seen.contours[0], seen.valid[0], size, 1.0)
        scale = image_scale(cam, ref).to(torch.float64)
        r, _ = _FrameResidual(model, scales, seen, layout, truth, sampler, chosen, None, scale)(
            x, rows
        )
        e_p = r[0, : seen.contours[0].shape[1]]
        return float((e_p * e_p).sum().sqrt())

    low, high = rms(camera, SIZE, reference), rms(sharp, (640, 512), reference)
    assert low > 1.0
    assert high == pytest.approx(low, rel=0.15)
    assert rms(sharp, (640, 512), None) == pytest.approx(2 * low, rel=0.15)

    # a solved frame reports its RMS in the image's pixels, the limits read reference pixels
    o = TrackOptions(iterations=2, rounds=1, reference_px_per_m=reference)
    seen = person_data_from_masks(_masks(model, sharp, truth)[:, None], sharp, stride=3)
    res = solve_frame(model, scales, seen, PoseLayout(model, o), x, x, o)
    torch.testing.assert_close(res.image_scale, torch.full((1,), 0.5, dtype=torch.float64))
    torch.testing.assert_close(res.reference_rms, 0.5 * res.contour_rms)
    with pytest.raises(ConfigError, match="track.reference_px_per_m"):
        TrackOptions(reference_px_per_m=0.0)


@pytest.mark.parametrize(
    "change, key",
    [
        ({"rounds": 0}, "track.rounds"),
        ({"iterations": 1.5}, "track.iterations"),
        ({"contour_stride": 0}, "track.contour_stride"),
        ({"initial_damping": 0.0}, "track.initial_damping"),
        ({"min_diag": float("nan")}, "track.min_diag"),
        ({"floor_weight": -1.0}, "track.floor_weight"),
        ({"confidence_px": 0.0}, "track.confidence_px"),
        ({"turn_smoothing": 1.5}, "track.turn_smoothing"),
        ({"distance_margin_px": -1}, "track.distance_margin_px"),
        ({"recover_every": 0}, "track.recover_every"),
        ({"jacobian": "bogus"}, "track.jacobian"),
    ],
)
def test_bad_tracker_options_are_config_errors_naming_the_key(change, key):
    """A tracker option out of its range fails when the options are made (the config's load,
    exit code 2), naming the key; a zero of a count used to crash mid-track."""
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        TrackOptions(**change)


def test_kept_silhouettes_unpack_to_themselves():
    """The overlays' silhouettes, kept as bounding boxes packed eight pixels to a byte, come
    back as they were, an empty one (no person found) included."""
    from torchfit.image import unpack_mask
    from torchfit.pipeline.track import _pack

    masks = torch.zeros(3, 6, 11, dtype=torch.bool)
    masks[1, 2:4, 3:10] = True
    masks[2, 0, 10] = masks[2, 5, 0] = True  # a box corner to corner
    for row, packed in zip(masks, _pack(masks), strict=True):
        assert np.array_equal(unpack_mask(packed) > 0, row.numpy())
