"""Track B sequences together, one frame per batch row (:func:`track`).

Per frame: each sequence's image is segmented against its background
(:func:`torchfit.image.segment`), the person data are made as for the fit
(:func:`torchfit.fit.person.person_data_from_masks`), and :func:`torchfit.track.frame.
solve_frame` fits every row's pose, warm-started and pulled towards the prediction
``x_{t-1} + d (x_{t-1} - x_{t-2})`` (``d`` the options' ``velocity_damping``: 1
extrapolates the last velocity, 0 holds the last pose; a silhouette leaves some directions
unseen, and a velocity extrapolated along them makes the pose drift), with the root's turn
about the vertical carried on at its recent rate (``turn_velocity``: front and back draw the
same silhouette, and a person turning through the side view was otherwise followed back the
way they came).

Recovery: a row whose contour RMS exceeds ``recover_factor`` times its sequence's running
median of good frames (and at least ``recover_min_px``; before any good frame,
:data:`torchfit.track.options.LOST_CONFIDENCE` times ``confidence_px``) is solved again from
its last good frame (or its start), pulled towards that frame (not the extrapolation) and
with twice the iterations, and in the same batch from its own pose with both arms raised
sideways (``recover_arms_deg``): an arm the solve left inside the body's outline, beside or in
front of the trunk, gets no pull from the silhouette's arm outside it (and the last good frame
had it there too), while an arm raised where the person's is not is pulled back in by the
model contour's own term; the best contour is kept. The frame's status is ``recovered`` when
that brings it back under the threshold, ``uncertain`` otherwise; after either the velocity is
reset (the next frame starts from this pose, not an extrapolation of a bad one), so one bad
frame does not throw the next ones. A frame's extra solves (these, and those to a second
silhouette below) are rows of one batch: two rows cost little more than one.
``confidence = 1 / (1 + (rms / confidence_px)²)``. The RMS these read is in reference pixels
(``reference_px_per_m``), the records' ``contour_rms`` in the image's. A
single camera cannot tell some poses apart (an arm in front of or behind the body), and the
contour RMS cannot either; the confidence says how well the silhouette is explained, not
which of those poses is right.

Second silhouettes: a frame handed over as a :class:`FrameSilhouettes` (light legs the shadow
test lost, given back by the bridge) is solved to a row's second silhouette where the
predicted pose draws the body over what it adds, or else where a solve to it, from the
prediction or from it with the legs at their neutral angles, explains it better
(:mod:`torchfit.track.silhouettes`); the row's record is then ``bridged``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, fields, replace

import torch

from torchfit.body.model import BodyModel
from torchfit.body.rotations import heading, turn_about_vertical
from torchfit.camera import Camera
from torchfit.fit.model_contour import EdgeSampler
from torchfit.fit.person import PersonData, person_data_from_masks
from torchfit.track.frame import FrameResult, PoseLayout, TrackOptions, solve_frame
from torchfit.track.options import LOST_CONFIDENCE
from torchfit.track.silhouettes import (
    SECOND_BETTER,
    SECOND_TRIAL_EVERY,
    FrameSilhouettes,
    expected,
    joined,
)

__all__ = ["FrameRecord", "FrameSilhouettes", "frame_data", "track"]


@dataclass
class FrameRecord:
    """One tracked frame of one sequence."""

    frame: int
    status: str
    cost: float
    iterations: int
    ms: float
    contour_rms: float
    confidence: float
    x: torch.Tensor = field(repr=False)
    bridged: bool = False  # tracked to the frame's second silhouette (FrameSilhouettes)


def _wrapped(a: torch.Tensor) -> torch.Tensor:
    """Angles into [-π, π)."""
    return torch.remainder(a + torch.pi, 2 * torch.pi) - torch.pi


def _predict(
    prev: torch.Tensor, prev2: torch.Tensor, rate: torch.Tensor, options: TrackOptions
) -> torch.Tensor:
    """The prediction before the limits: the last pose plus ``velocity_damping`` times its
    velocity, its root turned about the vertical by ``turn_velocity`` times the turn rate
    ``rate`` (B,) (radians per frame) less ``turn_dead_deg``."""
    pred = prev + options.velocity_damping * (prev - prev2)  # a new tensor, written below
    if options.turn_velocity:
        turn = torch.sign(rate) * (rate.abs() - math.radians(options.turn_dead_deg)).clamp_min(0)
        pred[:, 3:6] = turn_about_vertical(prev[:, 3:6], options.turn_velocity * turn)
    return pred


#: the leg joints a solve to a second silhouette also starts from at their neutral angles
_LEG_DOFS = ("hip_flexion", "hip_abduct", "knee_flexion", "ankle_flexion")


def _keep_better(res, ref: torch.Tensor, rows: torch.Tensor, other, factor: float = 1.0):
    """Where ``other`` (a solve of the rows ``rows`` of ``res``) explains the silhouette
    better (its contour RMS below ``factor`` times ``ref``'s), take its pose, contour RMS
    (``ref``) and cost; add its iterations either way. Returns the rows that took it."""
    took = []
    for k, i in enumerate(rows.tolist()):
        if float(other.reference_rms[k]) < factor * float(ref[i]):
            res.x[i] = other.x[k]
            ref[i] = other.reference_rms[k]
            res.cost[i] = other.cost[k]
            took.append(i)
        res.iterations[i] += other.iterations[k]
    return took


def _split(res: FrameResult, sizes: list[int]) -> list[FrameResult]:
    """A solve's result cut into consecutive groups of rows of these sizes."""
    names, at, out = [f.name for f in fields(FrameResult)], 0, []
    for n in sizes:
        out.append(FrameResult(*(getattr(res, name)[at : at + n] for name in names)))
        at += n
    return out


def _solve(model, layout, sampler, groups: list[tuple]) -> list[FrameResult]:
    """Rows of a frame solved in one batch (a solve costs little more for more rows). Each
    group ``(person, scales, start, options)`` holds n rows' person data, scales (n, S, 3) and
    start (n, P), solved from the start and pulled towards it; its rows take its
    ``options.iterations``, the other options are the first group's. A row's solve is the one
    it would have alone. One :class:`FrameResult` per group."""
    person, scales, x0, options = groups[0]
    if len(groups) == 1:
        return [solve_frame(model, scales, person, layout, x0, x0, options, sampler)]
    person = joined(*(g[0] for g in groups))
    scales = torch.cat([g[1] for g in groups])
    x0 = torch.cat([g[2] for g in groups])
    its = [g[3].iterations for g in groups for _ in range(len(g[2]))]
    limits = None if len(set(its)) == 1 else torch.tensor(its)
    res = solve_frame(model, scales, person, layout, x0, x0, options, sampler, limits)
    return _split(res, [len(g[2]) for g in groups])


def _median(values: list[float]) -> float:
    s = sorted(values[-30:])
    return s[len(s) // 2]


def frame_data(
    masks: torch.Tensor, cameras: Camera, options: TrackOptions, dtype: torch.dtype
) -> PersonData:
    """The person data the tracker fits one frame to: (B, H, W) silhouettes -> contours and
    distance maps (one silhouette per row). They depend on the images only, so a caller may
    make them ahead, e.g. where the next frames are read and segmented."""
    return person_data_from_masks(
        masks[:, None],
        cameras,
        stride=options.contour_stride,
        dtype=dtype,
        crop_margin_px=options.distance_margin_px,
    )


def track(
    model: BodyModel,
    scales: torch.Tensor,
    cameras: Camera,
    masks: Iterable[torch.Tensor | PersonData],
    x_start: torch.Tensor,
    options: TrackOptions | None = None,
    progress: Callable[[Iterator], Iterator] | None = None,
) -> list[list[FrameRecord]]:
    """Track B sequences.

    Args:
        model: the body model.
        scales: (B, S, 3) fixed segment scales per sequence.
        cameras: B cameras.
        masks: per frame, (B, H, W) bool silhouettes (a sequence that has ended repeats its
            last mask; the caller drops those frames), their :func:`frame_data`, or a
            :class:`FrameSilhouettes` (a second silhouette for some rows, taken where the
            predicted pose draws the body over what it adds or a solve to it fits better).
        x_start: (B, P) the pose rows of the frame before the first.
        options: tracker options.
        progress: wraps the frame iterator.

    Returns:
        Per sequence, its frame records.
    """
    options = options or TrackOptions()
    layout = PoseLayout(model, options)
    sampler = EdgeSampler(model.faces, options.samples_per_edge)
    b = scales.shape[0]
    prev = x_start.clone()
    prev2 = x_start.clone()
    rate = torch.zeros(b, dtype=x_start.dtype, device=x_start.device)  # turn per frame
    facing = heading(prev[:, 3:6])  # the last pose's heading
    good = x_start.clone()
    lost = [0] * b  # frames in a row over their limit
    refused = [0] * b  # frames in a row with a second silhouette not taken
    history: list[list[float]] = [[] for _ in range(b)]
    out: list[list[FrameRecord]] = [[] for _ in range(b)]
    it = iter(masks)
    if progress is not None:
        it = progress(it)
    # a bad frame is solved again from the last good one, pulled towards it, for longer
    recovery = replace(options, iterations=2 * options.iterations)
    # with no good frame yet, a contour that far off is all that can be told lost
    first = max(options.recover_min_px, LOST_CONFIDENCE * options.confidence_px)
    # the shoulders' sideways raise in a pose row (a template without them: no such re-solve)
    names = model.dof_names
    abduct = [6 + names.index(n) for n in ("l_shoulder_abduct", "r_shoulder_abduct") if n in names]
    legs = [6 + k for k, n in enumerate(names) if n.split("_", 1)[-1] in _LEG_DOFS]
    for f, mask in enumerate(it):
        t0 = time.perf_counter()
        second = mask if isinstance(mask, FrameSilhouettes) else None
        if second is not None:
            person = second.person
        elif isinstance(mask, PersonData):
            person = mask
        else:
            person = frame_data(mask, cameras, options, model.dtype)
        pred = layout.clip(_predict(prev, prev2, rate, options))
        bridged = [False] * b
        if second is not None:
            # a row's second silhouette where the predicted pose draws the body over what it
            # adds, or else where a solve to it explains it better than the first's solve
            bridged = expected(model, scales, cameras, pred, second)
            person = second.chosen(bridged, cameras, options, model.dtype)
        trials = []  # solves to the second silhouettes: more rows of the frame's solve
        if second is not None:
            # the solve to the second silhouette: in a stretch of frames whose second one was
            # refused, every SECOND_TRIAL_EVERY-th (the frames of a stretch are alike)
            rest = [i for i in range(b) if bool(second.has[i]) and not bridged[i]]
            for i in range(b):
                refused[i] = refused[i] + 1 if i in rest else 0
            rest = [i for i in rest if (refused[i] - 1) % SECOND_TRIAL_EVERY == 0]
            if rest:
                idx = torch.tensor(rest)
                other = second.second_data(cameras, options, model.dtype).subset(idx)
                starts = [pred[idx]]
                if legs:
                    # a leg the prediction hides behind the other, or folds into the stumps the
                    # first silhouette kept, is not where the second one shows it: the legs at
                    # their neutral angles too, pulled there
                    straight = pred[idx].clone()
                    straight[:, legs] = 0.0
                    starts.append(straight)
                trials = [(other, scales[idx], start, recovery) for start in starts]
        res, *alts = _solve(model, layout, sampler, [(person, scales, pred, options), *trials])
        if alts:
            took = []
            for alt in alts:
                took += _keep_better(res, res.reference_rms, idx, alt, SECOND_BETTER)
            took = sorted(set(took))
            if took:
                for i in took:
                    bridged[i], refused[i] = True, 0
                person = second.chosen(bridged, cameras, options, model.dtype)
        status = ["ok"] * b
        limit = [
            max(options.recover_min_px, options.recover_factor * _median(h)) if h else first
            for h in history
        ]
        # the limits, the history and the confidence are in reference pixels
        ref = res.reference_rms
        over = [i for i in range(b) if float(ref[i]) > limit[i]]
        # in a stretch of them, the first few, then every recover_every-th
        n = options.recover_every
        bad = [i for i in over if lost[i] < n - 1 or lost[i] % n == 0]
        for i in over:
            status[i] = "uncertain"  # unless solved again below, and then within its limit
        if bad:
            idx = torch.tensor(bad)
            # from the last good frame, pulled towards it; and from the frame's own pose with
            # both arms raised sideways: an arm the solve left inside the body's outline gets
            # no pull from the silhouette, nor does a start from the last good frame, which had
            # it there too (an arm raised where the person's is not is pulled back in by the
            # model contour's own term)
            starts = [good[idx]]
            if options.recover_arms_deg and abduct:
                raised = res.x[idx].clone()
                raised[:, abduct] = math.radians(options.recover_arms_deg)
                starts.append(raised)
            sub = person.subset(idx)
            groups = [(sub, scales[idx], start, recovery) for start in starts]
            for alt in _solve(model, layout, sampler, groups):
                _keep_better(res, ref, idx, alt)
            for i in bad:
                status[i] = "recovered" if float(ref[i]) <= limit[i] else "uncertain"
        ms = 1000 * (time.perf_counter() - t0) / b
        for i in range(b):
            rms = float(ref[i])
            lost[i] = lost[i] + 1 if status[i] == "uncertain" else 0
            if status[i] != "uncertain":
                history[i].append(rms)
                good[i] = res.x[i]
            out[i].append(
                FrameRecord(
                    frame=f,
                    status=status[i],
                    cost=float(res.cost[i]),
                    iterations=int(res.iterations[i]),
                    ms=ms,
                    contour_rms=float(res.contour_rms[i]),  # the image's pixels
                    confidence=1.0 / (1.0 + (rms / options.confidence_px) ** 2),
                    x=res.x[i].detach().clone(),
                    bridged=bridged[i],
                )
            )
        okay = torch.tensor([s == "ok" for s in status], device=res.x.device)
        # the turn rate: from the second frame on, over frames ok in a row
        now = heading(res.x[:, 3:6])
        turned, facing = _wrapped(now - facing), now
        a = options.turn_smoothing
        rate = torch.where(okay & (f > 0), a * rate + (1 - a) * turned, torch.zeros_like(rate))
        prev2 = torch.where(okay[:, None], prev, res.x)
        prev = res.x.detach().clone()
    return out
