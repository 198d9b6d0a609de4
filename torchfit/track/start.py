"""The first frame of a sequence: pose hypotheses solved together, the best contour kept
(:func:`start_poses`).

The person is assumed to face the camera roughly: the start is the neutral pose facing the
camera, standing where the silhouette's lowest point meets the floor (or, for someone in the
air, where the neutral model's height fills the silhouette's), with yaw hypotheses within ±45°
of facing the camera. A silhouette looks the same from the front and from the back (left and
right swapped); after the first frame the temporal term keeps the side.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import torch

from torchfit.body.model import BodyModel
from torchfit.body.postures import facing_yaw, nominal_joint_angles
from torchfit.camera import Camera, camera_centre, floor_points, ray_directions
from torchfit.fit.model_contour import EdgeSampler
from torchfit.fit.person import PersonData
from torchfit.track.frame import solve_frame
from torchfit.track.options import LOST_CONFIDENCE, PoseLayout, TrackOptions
from torchfit.track.tracker import frame_data

__all__ = ["start_poses"]

log = logging.getLogger(__name__)

#: first-frame yaw hypotheses around facing the camera, radians.
_TURNS = tuple(math.radians(d) for d in (-45.0, -20.0, 0.0, 20.0, 45.0))

#: the first frame's sized placement is kept when its contour RMS is this many times lower
#: than the floor placement's.
_OFF_FLOOR = 2.0
#: the first frame's sized placement is solved only where its root lies this far (metres) or
#: more from the floor placement's: nearer, the silhouette's height agrees with a body standing
#: on the floor there (on the thirty development clips the seven that take the sized placement
#: have theirs 0.63-1.33 m apart, the others 0.06-0.37 m)
_SIZED_APART = 0.5
#: the first frame's hypotheses solved together, at most (whole sequences' sets of them)
_START_ROWS = 20


def start_poses(
    model: BodyModel,
    scales: torch.Tensor,
    cameras: Camera,
    mask: torch.Tensor,
    layout: PoseLayout,
    options: TrackOptions,
    person: PersonData | None = None,
) -> torch.Tensor:
    """First-frame rows: per sequence, one or two placements times yaw hypotheses, the best
    contour kept (tried again from the T-pose where that contour is far off). Standing: the
    silhouette's lowest pixel on the floor; sized: at the distance where the neutral model's
    height fills the silhouette's height (a person in mid-jump in the first frame is not on the
    floor, and the floor placement puts them far behind), solved where it lies
    :data:`_SIZED_APART` or more from the standing one.

    Args:
        model: the body model.
        scales: (B, S, 3) each sequence's segment scales.
        cameras: B cameras.
        mask: (B, H, W) the first frames' silhouettes.
        layout: the pose layout.
        options: tracker options (the start runs three rounds of three times its iterations).
        person: the first frames' :func:`torchfit.track.frame_data`, if the caller has them.

    Returns:
        (B, P) the first frames' pose rows.
    """
    dt = model.dtype
    person = person if person is not None else frame_data(mask, cameras, options, dt)
    hanging = torch.zeros(model.num_dofs, dtype=dt)
    x, rms = _best_start(model, scales, cameras, mask, layout, options, person, hanging)
    # a start that hardly explains its silhouette (confidence under 0.1) is tried again with
    # the arms raised sideways: from hanging arms the solve does not lift them, and a
    # calibration T-pose starts many captures
    lost = (rms > LOST_CONFIDENCE * options.confidence_px).nonzero().flatten()
    if lost.numel():
        log.info("first frame: %d sequence(s) tried again from the T-pose", lost.numel())
        raised = nominal_joint_angles(model.dof_names, 4, dt)
        sub = (scales[lost], cameras[lost], mask[lost], layout, options, person.subset(lost))
        y, rms_raised = _best_start(model, *sub, raised)
        better = rms_raised < rms[lost]
        x[lost[better]] = y[better]
    return x


def _best_start(model, scales, cameras, mask, layout, options, person, arms):
    """The best of one arm pose's hypotheses per sequence: (B, P) rows and (B,) contour RMS."""
    b = scales.shape[0]
    dt = model.dtype
    centre = camera_centre(cameras.R, cameras.t).to(dt)
    yaw0 = facing_yaw(centre)
    with torch.no_grad():
        z = model(scales, **{k: v for k, v in model.zeros(b).items() if k != "scales"})
        z = z.vertices[..., 2]
    rows, fixed_z = [], []  # per hypothesis: its pose and its fixed height
    counts = []  # per sequence, its hypotheses (the floor's, then the sized ones where any)
    for i in range(b):
        ys, xs = torch.nonzero(mask[i], as_tuple=True)
        cam = cameras[[i]]
        k, c = cam.K[0].to(dt), centre[i]
        u = float(xs.float().mean())
        top, bottom = float(ys.min()), float(ys.max())
        pixels = torch.tensor([[[u, bottom], [u, 0.5 * (top + bottom)]]], dtype=dt)
        # standing: the floor point under the silhouette's lowest pixel (the camera's own
        # spot where that pixel sees no floor)
        ground = floor_points(pixels[:, :1], cam)[0, 0]
        ground = torch.where(torch.isnan(ground), c, ground)
        # sized: the body's mid-height on the ray through the silhouette's mid-height
        height = float(z[i].max() - z[i].min())
        depth = float(k[1, 1]) * height / max(bottom - top, 1.0)
        sized = c + depth * ray_directions(pixels[:, 1:], cam)[0, 0]
        sized[2] -= 0.5 * float(z[i].max() + z[i].min())
        places = [(ground, None)]
        standing = torch.cat([ground[:2], -z[i].min()[None]])  # the root, standing there
        if float((sized - standing).norm()) >= _SIZED_APART:
            places.append((sized, float(sized[2])))
        for place, pz in places:
            for turn in _TURNS:
                x = torch.zeros(layout.num_params, dtype=dt)
                x[:2] = place[:2]
                x[5] = yaw0[i] + turn
                x[6:] = arms
                rows.append(x)
                fixed_z.append(pz)
        counts.append(len(places) * len(_TURNS))
    x0 = torch.stack(rows)
    owner = torch.arange(b).repeat_interleave(torch.tensor(counts))
    sc = scales[owner]
    # the root height: standing, the model's lowest point on the floor
    with torch.no_grad():
        t, r, q = PoseLayout.split(x0)
        low = model(sc, q, t, r).vertices[..., 2].min(1).values
    for j, pz in enumerate(fixed_z):
        x0[j, 2] = -low[j] if pz is None else pz
    # the distance maps once per sequence, shared by its hypotheses
    person = person.subset(owner)
    # held towards the neutral start by the tracker's own temporal weights and priors (the
    # layout's), the root at start_translation; free root and 0.5 px/rad on the joints gave
    # worse starts on 01_01 clips (mean joint error 182, 65, 140 mm against 83, 79, 114 mm)
    opts = replace(
        options,
        iterations=3 * options.iterations,
        rounds=3,
        temporal_translation=options.start_translation,
    )
    log.info("first frame: %d pose hypotheses for %d sequence(s)", len(rows), b)
    sampler = EdgeSampler(model.faces, options.samples_per_edge)  # once for every chunk
    # a few sequences' hypotheses at a time: a row's solve does not depend on the others, and
    # past a few dozen rows the Jacobians outgrow the caches (eight sequences' 80 rows at
    # once took 0.65 s a sequence, 20 at a time 0.33, as one sequence's alone)
    xs, rms = [], []
    for chunk in _chunks(counts):
        res = solve_frame(
            model, sc[chunk], person.subset(chunk), layout, x0[chunk], x0[chunk], opts, sampler
        )
        xs.append(res.x)
        rms.append(res.reference_rms)
    x, rms = torch.cat(xs), torch.cat(rms)
    # the floor placement unless the sized one explains the silhouette far better (someone
    # standing fits both, and their contours do not tell a lean or a depth apart)
    n, best, first = len(_TURNS), [], 0
    for count in counts:
        pick = first + int(rms[first : first + n].argmin())
        if count > n:
            sized = first + n + int(rms[first + n : first + count].argmin())
            if float(rms[sized]) * _OFF_FLOOR < float(rms[pick]):
                pick = sized
        best.append(pick)
        first += count
    return x[best], rms[best]


def _chunks(counts: list[int]) -> list[torch.Tensor]:
    """The hypothesis rows of sequences with ``counts`` rows each, in chunks of whole
    sequences, at most :data:`_START_ROWS` rows each (more where one sequence has more)."""
    chunks, start, size = [], 0, 0
    for count in counts:
        if size and size + count > _START_ROWS:
            chunks.append(torch.arange(start, start + size))
            start, size = start + size, 0
        size += count
    return chunks + [torch.arange(start, start + size)]
