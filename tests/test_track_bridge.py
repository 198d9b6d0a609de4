"""A tracked frame's second silhouette (``track.bridge_min``): where the shadow test took the
person's light trousers for the wall's shadow, the frame is segmented again with those pixels
given back, and the tracker takes that silhouette where the body it expects lies over what it
adds, not where it adds a shadow beside the body."""

import numpy as np
import pytest
import test_track
import torch
from test_track import SIZE, _empty_sequence, _pose

from torchfit.camera import project_points
from torchfit.errors import ConfigError
from torchfit.track import PoseLayout, TrackOptions, frame_data, track, tracker
from torchfit.track.silhouettes import SECOND_TRIAL_EVERY, FrameSilhouettes, expected, placed
from torchfit.viz.raster import render_silhouette

# test_track's module fixtures, shared
model, camera = test_track.model, test_track.camera

FRAMES = 6
LEGS = ("thigh", "calf")


def _silhouettes(model, camera, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, H, W) silhouettes of the whole body, and of the thighs' and calves' pixels that
    no other part covers, at the rows x."""
    scales = torch.ones(x.shape[0], model.num_segments, 3, dtype=torch.float64)
    t, r, q = PoseLayout.split(x)
    with torch.no_grad():
        pix = project_points(model(scales, q, t, r).vertices, camera[[0] * x.shape[0]])
    faces = model.faces.numpy()
    names = model.template.segments
    seg = model.template.vertex_segment.numpy()
    leg = np.array([any(k in names[s] for k in LEGS) for s in seg])[faces].all(1)

    def render(f):
        return np.stack([render_silhouette(p.numpy(), f, SIZE) > 0 for p in pix])

    whole = render(faces)
    return torch.from_numpy(whole), torch.from_numpy(render(faces[leg]) & ~render(faces[~leg]))


def _sequence(model, camera):
    """The left arm waving, the legs still; from frame 2 on the first silhouettes have lost
    the thighs and calves (the feet stay)."""
    layout = PoseLayout(model, TrackOptions())
    angles = [{"l_shoulder_abduct": 0.3 + 0.12 * k, "r_hip_abduct": 0.2} for k in range(FRAMES)]
    xs = torch.stack([_pose(model, layout, camera, a) for a in angles])
    whole, legs = _silhouettes(model, camera, xs)
    first = whole.clone()
    first[2:] &= ~legs[2:]
    return xs, whole, first


def _leg_error_mm(model, x: torch.Tensor, xs: torch.Tensor) -> np.ndarray:
    """Per frame, the mean distance of the knees and ankles of rows x from the truth xs, mm."""
    scales = torch.ones(xs.shape[0], model.num_segments, 3, dtype=torch.float64)
    with torch.no_grad():
        a = model.joint_positions(model(scales, x[:, 6:], x[:, :3], x[:, 3:6]))
        b = model.joint_positions(model(scales, xs[:, 6:], xs[:, :3], xs[:, 3:6]))
    names = ("l_knee", "r_knee", "l_ankle", "r_ankle")
    return 1000 * torch.stack([(a[n] - b[n]).norm(dim=-1) for n in names], 1).mean(1).numpy()


def _track(model, camera, xs, frames, opts):
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    recs = track(model, scales, camera, iter(frames), xs[:1], opts)[0]
    return recs, _leg_error_mm(model, torch.stack([r.x for r in recs]), xs)


def _frames(camera, first, second, opts):
    """FrameSilhouettes of one sequence: ``second[k]`` None for no second silhouette."""
    out = []
    for k in range(FRAMES):
        person = frame_data(first[k : k + 1], camera, opts, torch.float64)
        if second[k] is None:
            out.append(person)
            continue
        has = torch.tensor([True])
        out.append(FrameSilhouettes(person, first[k : k + 1], second[k][None], has))
    return out


OPTS = TrackOptions(iterations=3, rounds=2)


def test_a_second_silhouette_that_gives_the_legs_back_is_taken(model, camera):
    """Frames whose first silhouette lost the legs and whose second has them: the tracker
    takes the second (``bridged``), and the legs are tracked as with the whole silhouettes;
    with the first ones alone the model's legs are drawn up into what is left."""
    xs, whole, first = _sequence(model, camera)
    second = [None, None] + [whole[k] for k in range(2, FRAMES)]
    recs, err = _track(model, camera, xs, _frames(camera, first, second, OPTS), OPTS)
    _, alone = _track(model, camera, xs, _frames(camera, first, [None] * FRAMES, OPTS), OPTS)
    _, right = _track(model, camera, xs, _frames(camera, whole, [None] * FRAMES, OPTS), OPTS)
    print("knees and ankles, mm: second", err, "first alone", alone, "whole", right)
    assert [r.bridged for r in recs] == [False, False] + [True] * (FRAMES - 2)
    np.testing.assert_allclose(err, right, atol=1e-6)
    assert alone[2:].mean() > 3 * err[2:].mean() + 20, (alone, err)


def test_a_second_silhouette_the_prediction_misses_is_taken_where_it_fits_better(model, camera):
    """Every frame lost its legs, and the first is tracked from a pose 25 cm to the side: the
    predicted body lies beside the legs the second silhouette gives back, but a solve to the
    second explains it better than the solve to the first, so it is taken there too, and the
    legs are tracked nearer than to the first silhouettes alone."""
    xs, whole, _ = _sequence(model, camera)
    first = whole & ~_silhouettes(model, camera, xs)[1]
    second = [whole[k] for k in range(FRAMES)]
    start = xs[:1].clone()
    start[0, 1] += 0.25
    frames = _frames(camera, first, second, OPTS)
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    recs = track(model, scales, camera, iter(frames), start, OPTS)[0]
    err = _leg_error_mm(model, torch.stack([r.x for r in recs]), xs)
    alone = track(
        model, scales, camera, iter(_frames(camera, first, [None] * FRAMES, OPTS)), start, OPTS
    )[0]
    err_alone = _leg_error_mm(model, torch.stack([r.x for r in alone]), xs)
    print("knees and ankles, mm: second", err, "first alone", err_alone)
    assert expected(model, scales, camera, start, frames[0]) == [False]
    assert all(r.bridged for r in recs), [r.bridged for r in recs]
    assert err.mean() < 0.5 * err_alone.mean(), (err, err_alone)


def test_the_solves_to_the_second_silhouette_are_rows_of_the_frames_solve(model, camera):
    """A frame tried on its second silhouette is one solve: the frame's row with its own
    iterations, and the two solves to the second (from the prediction, and with the legs
    straight) with twice as many; the tracks are those of the separate solves (the test
    above's)."""
    xs, whole, _ = _sequence(model, camera)
    first = whole & ~_silhouettes(model, camera, xs)[1]
    start = xs[:1].clone()
    start[0, 1] += 0.25
    frames = _frames(camera, first, [whole[k] for k in range(FRAMES)], OPTS)
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    calls = []
    solve = tracker.solve_frame

    def counted(*a, **k):
        limits = a[8] if len(a) > 8 else k.get("iterations")
        calls.append((a[4].shape[0], None if limits is None else limits.tolist()))
        return solve(*a, **k)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(tracker, "solve_frame", counted)
        track(model, scales, camera, iter(frames), start, OPTS)
    trials = [c for c in calls if c[0] == 3]
    assert trials and all(c[1] == [3, 6, 6] for c in trials), calls
    assert all(c in ((1, None), (3, [3, 6, 6])) for c in calls), calls


def test_legs_spread_off_the_stumps_are_brought_back_by_the_solve_to_the_second(model, camera):
    """Every frame lost its legs, and the tracking starts with both legs spread far to the sides
    (as a start solved to the stumps can leave them): neither the prediction nor a solve from
    it reaches the legs the second silhouette shows, the solve from the legs at their neutral
    angles does, and the legs are tracked from the first frame on."""
    xs, whole, _ = _sequence(model, camera)
    first = whole & ~_silhouettes(model, camera, xs)[1]
    start = xs[:1].clone()
    for name in ("l_hip_abduct", "r_hip_abduct"):
        start[0, 6 + model.dof_index(name)] = 0.9
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    frames = _frames(camera, first, [whole[k] for k in range(FRAMES)], OPTS)
    assert expected(model, scales, camera, start, frames[0]) == [False]
    recs = track(model, scales, camera, iter(frames), start, OPTS)[0]
    err = _leg_error_mm(model, torch.stack([r.x for r in recs]), xs)
    print("knees and ankles, mm:", err)
    assert all(r.bridged for r in recs), [r.bridged for r in recs]
    assert err.max() < 40, err


def _with_patch(mask: torch.Tensor) -> torch.Tensor:
    """The silhouette with a 10 x 30 px patch joined to the feet, beside them (a floor shadow
    between the feet and a part cut off below, as the bridge gives it back)."""
    ys, us = torch.nonzero(mask, as_tuple=True)
    feet = us[ys > ys.max() - 20]
    out = mask.clone()
    v0, u0 = int(ys.max()) - 12, int(feet.max()) - 3
    out[v0 : v0 + 10, u0 : u0 + 30] = True
    return out


def test_a_second_silhouette_that_adds_a_shadow_beside_the_body_is_not_taken(model, camera):
    """A second silhouette that adds a patch beside the feet (a floor shadow between them and
    a part cut off below) is not where the body is expected, nor does a solve to it fit
    better: the frames are tracked to their first silhouettes, exactly as without a second
    one."""
    xs, whole, _ = _sequence(model, camera)
    second = [_with_patch(whole[k]) if k >= 2 else None for k in range(FRAMES)]
    recs, err = _track(model, camera, xs, _frames(camera, whole, second, OPTS), OPTS)
    plain, same = _track(model, camera, xs, _frames(camera, whole, [None] * FRAMES, OPTS), OPTS)
    assert not any(r.bridged for r in recs)
    assert all(torch.equal(a.x, b.x) for a, b in zip(recs, plain, strict=True))
    np.testing.assert_array_equal(err, same)
    # the solve to the refused second silhouette (its iterations are counted) is made in the
    # first frame of the stretch and then every SECOND_TRIAL_EVERY-th
    tried = [k for k in range(FRAMES) if recs[k].iterations > plain[k].iterations]
    assert tried == list(range(2, FRAMES, SECOND_TRIAL_EVERY)), tried


def _light_legs_sequence(model, tmp_path):
    """A two-frame sequence before a flat grey wall, its own camera (legs wide enough for the
    shadow test's window): frame 0 in coloured trousers, frame 1 in trousers a darker copy of
    the wall, their edge fading into it, with dark shoes. Returns the folder and frame 1's
    thigh and calf pixels."""
    import cv2

    from torchfit.viz.preview import nominal_view

    size = (400, 480)
    cam = nominal_view(distance=3.0, azimuth_deg=0.0, focal=700.0, image_size=size)
    layout = PoseLayout(model, TrackOptions())
    x = _pose(model, layout, cam, {"r_hip_abduct": 0.15, "l_hip_abduct": 0.15})[None]
    scales = torch.ones(1, model.num_segments, 3, dtype=torch.float64)
    t, r, q = PoseLayout.split(x)
    with torch.no_grad():
        pix = project_points(model(scales, q, t, r).vertices, cam)[0].numpy()
    faces = model.faces.numpy()
    names, seg = model.template.segments, model.template.vertex_segment.numpy()

    def part(keys):
        sel = np.array([any(k in names[s] for k in keys) for s in seg])[faces].all(1)
        return render_silhouette(pix, faces[sel], size) > 0

    whole = render_silhouette(pix, faces, size) > 0
    legs, feet = part(LEGS), part(("hindfoot",))
    legs &= ~part(("pelvis", "l5", "t10", "hand", "forearm", "hindfoot"))
    rng = np.random.default_rng(0)
    wall = (170 + rng.integers(0, 6, (size[1], size[0], 3))).astype(np.uint8)
    folder = _empty_sequence(tmp_path / "light_legs", cam, wall)
    coloured = wall.copy()
    coloured[whole] = (90, 150, 200)  # BGR
    coloured[legs] = (140, 60, 60)
    coloured[feet] = (30, 30, 30)
    light = coloured.copy()
    blur = cv2.GaussianBlur(legs.astype(np.float32), (0, 0), 8.0)
    alpha = np.maximum(legs.astype(np.float32), blur)
    soft = (alpha > 0.01) & ~(whole & ~legs) & ~feet
    light[soft] = (wall[soft] * (1 - 0.4 * alpha[soft, None])).astype(np.uint8)
    cv2.imwrite(str(folder / "frames" / "000000.png"), coloured)
    cv2.imwrite(str(folder / "frames" / "000001.png"), light)
    return folder, torch.from_numpy(legs)


def test_a_frame_whose_light_legs_pass_for_a_shadow_is_segmented_a_second_time(model, tmp_path):
    """``SequenceSegmenter.segmented``: light trousers fading into a flat wall are taken for
    its shadow and lost, but for their rims, between the body and the shoes; the frame gets a
    second silhouette, ``segmentation.shadow_bridge``'s, with the legs given back. The frame in
    coloured trousers, and every frame with ``bridge_min`` 0, gets none."""
    import dataclasses

    from torchfit.image import fit_background, segment
    from torchfit.io.images import list_images, load_frames
    from torchfit.pipeline.sequence import SequenceSegmenter
    from torchfit.pipeline.track import TrackConfig, load_sequence

    folder, legs = _light_legs_sequence(model, tmp_path)
    cfg = TrackConfig().segmentation
    seq = load_sequence(folder)
    got = list(SequenceSegmenter(seq, cfg, 0.05).segmented())
    (plain, none), (first, second) = got
    assert none is None and second is not None
    assert (plain & legs).sum() > 0.95 * legs.sum()
    assert (first & legs).sum() < 0.8 * legs.sum()
    assert (second & legs).sum() > (first & legs).sum() + 0.15 * legs.sum()
    size = seq.camera.image_size
    bg = fit_background(load_frames(list_images(folder / "background"), size)[0], cfg)
    image = load_frames([seq.frames[1]], size)[0]
    bridged = segment(image, bg, dataclasses.replace(cfg, shadow_bridge=True)).masks[0, 0]
    assert torch.equal(second, bridged) and torch.equal(first, segment(image, bg, cfg).masks[0, 0])
    assert all(s is None for _, s in SequenceSegmenter(seq, cfg, 0.0).segmented())


@pytest.mark.parametrize("value", [-0.1, float("nan"), True])
def test_a_bad_bridge_fraction_is_a_config_error(value):
    with pytest.raises(ConfigError, match="track.bridge_min"):
        TrackOptions(bridge_min=value)


def test_a_tracked_sequence_says_which_frames_took_their_second_silhouette(model, tmp_path):
    """``track_sequences`` on the light-trousers sequence: the second frame is tracked to its
    second silhouette (the first frame's pose draws the legs it gives back), ``track.csv``'s
    ``bridged`` column and the summary's ``bridged_frames`` say so, and its overlay draws that
    silhouette; with ``bridge_min`` 0 no frame is."""
    import csv

    from torchfit.pipeline.track import TrackConfig, load_sequence, track_sequences

    folder, _ = _light_legs_sequence(model, tmp_path)
    scales = torch.ones(model.num_segments, 3, dtype=torch.float64)
    got = {}
    for bridge in (0.05, 0.0):
        cfg = TrackConfig(track=TrackOptions(iterations=3, rounds=2, bridge_min=bridge))
        out = tmp_path / f"out_{bridge}"
        summary = track_sequences(
            model, scales, [load_sequence(folder)], [out], cfg, ahead="none", overlays=True
        )[0]
        with open(out / "track.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        got[bridge] = (summary["bridged_frames"], [r["bridged"] for r in rows])
        overlays = sorted((out / "overlay").glob("*.png"))
        got[bridge] += (overlays[1].read_bytes(),)
    assert got[0.05][:2] == (1, ["0", "1"]), got[0.05][:2]
    assert got[0.0][:2] == (0, ["0", "0"]), got[0.0][:2]
    assert got[0.05][2] != got[0.0][2]  # another silhouette drawn


def test_rows_that_take_and_refuse_their_second_silhouette_track_as_they_do_alone(model, camera):
    """Two sequences together, one taking its second silhouettes (lost legs given back), the
    other refusing them (a patch beside the feet): each row is tracked as it is alone, its
    person data taken row by row from the two silhouettes' (made ahead, as the reader does)."""
    xs, whole, first = _sequence(model, camera)
    patched = [_with_patch(whole[k]) for k in range(FRAMES)]
    cams = camera[[0, 0]]
    frames = []
    for k in range(FRAMES):
        masks = torch.stack([first[k], whole[k]])
        second = torch.stack([whole[k], patched[k]])
        person = frame_data(masks, cams, OPTS, torch.float64)
        has = torch.tensor([k >= 2, k >= 2])
        ahead = frame_data(second, cams, OPTS, torch.float64)
        frames.append(FrameSilhouettes(person, masks, second, has, ahead))
    scales = torch.ones(2, model.num_segments, 3, dtype=torch.float64)
    both = track(model, scales, cams, iter(frames), xs[[0, 0]], OPTS)
    alone = [
        _track(
            model, camera, xs, _frames(camera, first, [None, None] + list(whole[2:]), OPTS), OPTS
        )[0],
        _track(model, camera, xs, _frames(camera, whole, [None, None] + patched[2:], OPTS), OPTS)[
            0
        ],
    ]
    for row in range(2):
        assert [r.bridged for r in both[row]] == [r.bridged for r in alone[row]]
        for a, b in zip(both[row], alone[row], strict=True):
            torch.testing.assert_close(a.x, b.x, atol=1e-6, rtol=0)
    assert [r.bridged for r in both[0]][2:] == [True] * (FRAMES - 2)
    assert not any(r.bridged for r in both[1])


def test_the_second_silhouettes_data_made_for_the_rows_that_have_one(model, camera):
    """The reader makes the second silhouettes' contours and maps only for the rows that have
    one (``placed`` into the first's data): the batch tracks as with the data of every row."""
    xs, whole, first = _sequence(model, camera)
    cams = camera[[0, 0]]
    scales = torch.ones(2, model.num_segments, 3, dtype=torch.float64)
    runs = []
    for only_rows in (False, True):
        frames = []
        for k in range(FRAMES):
            masks = torch.stack([first[k], whole[k]])
            second = torch.stack([whole[k], whole[k]])  # row 1 has none: it holds its first
            has = torch.tensor([k >= 2, False])
            person = frame_data(masks, cams, OPTS, torch.float64)
            if not has.any():  # as the reader hands over a frame without second silhouettes
                frames.append(person)
                continue
            if only_rows:
                rows = has.nonzero().flatten()
                ahead = placed(
                    person, rows, frame_data(second[rows], cams[rows], OPTS, torch.float64)
                )
            else:
                ahead = frame_data(second, cams, OPTS, torch.float64)
            frames.append(FrameSilhouettes(person, masks, second, has, ahead))
        runs.append(track(model, scales, cams, iter(frames), xs[[0, 0]], OPTS))
    for row in range(2):
        for a, b in zip(runs[0][row], runs[1][row], strict=True):
            assert torch.equal(a.x, b.x) and a.bridged == b.bridged
    assert any(r.bridged for r in runs[1][0]) and not any(r.bridged for r in runs[1][1])
