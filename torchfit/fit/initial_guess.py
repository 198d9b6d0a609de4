"""Where the fit starts: the template at the nominal postures, or the automatic guess.

The automatic guess (``fit.initial_guess: parts``; the second paper used from one camera):

1. **Root position, every posture.** The lowest silhouette pixel is where the feet meet the
   floor. The template is posed at the posture's nominal angles, its lowest projected vertex
   found, and the floor translation moved so that the viewing ray of the person's lowest pixel
   and that vertex meet at the same floor point.
2. **Overall scale, posture 1.** The template's image height (head top to lowest foot pixel)
   is matched to the silhouette's by one scale factor on every segment.
3. **Arm segment scales, posture 5.** The rules of :func:`torchfit.parts.initial_guess_2d`
   label shoulders, elbows and (from skin colour) wrists; the model's own joint centres are
   projected at the posture-5 start, and the length axis of the upper arm and forearm groups
   is scaled by the ratio of the person's to the model's image lengths (averaged over the two
   sides). Both are measured at the same depth, so the camera's scale cancels.

Steps 1–2 repeat a few times (scale and foot position interact). A subject whose posture-5 rules
fail keeps the extents-based start (steps 1–2) with template arm proportions; one whose
posture-1 silhouette is empty keeps the template start. :class:`StartInfo` records which, and
why, for params.json.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from torchfit.errors import ConfigError
from torchfit.parts.options import PartsOptions

__all__ = ["StartInfo", "parts_start", "arm_ratios"]

#: A joint-length ratio outside this range is not trusted (a mislabelled cut, not a body).
PLAUSIBLE_RATIO = (0.7, 1.4)
#: Forearm/upper-arm length proportion, relative to the template's, that is still a body.
PLAUSIBLE_PROPORTION = (0.8, 1.25)
#: The lowest silhouette pixel counts as the feet within this fraction of the image height.
FOOT_TOLERANCE = 0.03


@dataclass
class StartInfo:
    """How one subject's start was made.

    Attributes:
        source: ``"template"``, ``"parts"`` (extents and posture-5 joints) or
            ``"parts_extents"`` (extents only; the posture-5 rules failed).
        message: why a source other than ``"parts"`` was used ("" otherwise).
        scale: the overall scale from the posture-1 height (None for the template).
        upperarm: upper arm length-axis scale (None where not estimated).
        forearm: forearm length-axis scale (None where not estimated).
    """

    source: str
    message: str = ""
    scale: float | None = None
    upperarm: float | None = None
    forearm: float | None = None

    def to_dict(self) -> dict:
        """The params.json form."""
        return asdict(self)


def _centroid_u(mask: np.ndarray) -> float:
    cols = np.nonzero(mask)[1]
    return float(cols.mean()) if len(cols) else float("nan")


def _place(fit, x, j, rows, head_obs, foot_obs, centre_obs, tolerance):
    """One update of pose j's sideways floor translation and the posture's height ratio.

    Returns:
        (B, 2) translation change (along the camera's horizontal x axis, matching the column of
        the silhouette's centroid with the rendered model's), the (B,) ratio of the person's to
        the model's image height, and (B,) whether the person's lowest pixel sits within
        ``tolerance`` (fraction of the height) of the model's foot. Where it does not (feet
        lost by the segmentation, a shadow kept), the ratio keeps the model's own foot and
        matches the head top alone.
    """
    from torchfit.viz.raster import render_silhouette

    verts, origins = fit.pose_world(x, j, rows)
    px = fit.project(verts, rows)
    pick = torch.arange(len(rows))
    top = px[..., 1].argmin(dim=1)
    head_v = px[pick, top, 1]
    foot_v = px[..., 1].max(dim=1).values
    height_model = (foot_v - head_v).clamp_min(1.0)
    feet_ok = (foot_obs[:, 1] - foot_v).abs() <= tolerance * height_model
    ratio = (torch.where(feet_ok, foot_obs[:, 1], foot_v) - head_obs[:, 1]) / height_model
    faces = fit.model.faces.cpu().numpy()
    size = fit.camera.image_size
    centre_model = torch.tensor(
        [_centroid_u(render_silhouette(p.cpu().numpy(), faces, size)) for p in px.detach()],
        **fit.kw,
    )
    cam = fit.camera
    R, t, K = cam.R[rows], cam.t[rows], cam.K[rows]
    depth = (R[:, 2] * origins[:, 0]).sum(-1) + t[:, 2]
    side = R[:, 0, :2] / torch.linalg.vector_norm(R[:, 0, :2], dim=-1, keepdim=True)
    shift = torch.nan_to_num((centre_obs - centre_model) * depth / K[:, 0, 0])
    return side * shift[:, None], ratio, feet_ok


def arm_ratios(
    person: dict[str, np.ndarray], model: dict[str, np.ndarray]
) -> tuple[dict[str, float], list[str]]:
    """Length ratios person/model of the upper arm and forearm in one image.

    Args:
        person: joint name -> ``(u, v)`` of the person (``{l,r}_{shoulder,elbow,wrist}``;
            missing joints are skipped).
        model: the same joints of the model, projected at the same depth.

    Returns:
        ``({"upperarm": r, "forearm": r}, notes)`` averaged over the sides; a ratio outside
        :data:`PLAUSIBLE_RATIO`, or a forearm whose proportion to the upper arm is outside
        :data:`PLAUSIBLE_PROPORTION` times the model's, is dropped with a note saying why.
    """
    ratio: dict[str, float] = {}
    for group, (a, c) in {"upperarm": ("shoulder", "elbow"), "forearm": ("elbow", "wrist")}.items():
        sides = []
        for side in "lr":
            names = (f"{side}_{a}", f"{side}_{c}")
            if not all(n in person and n in model for n in names):
                continue
            length_person = float(np.linalg.norm(np.subtract(person[names[1]], person[names[0]])))
            length_model = float(np.linalg.norm(np.subtract(model[names[1]], model[names[0]])))
            sides.append(length_person / max(length_model, 1e-6))
        if sides:
            ratio[group] = float(np.mean(sides))
    notes = []
    for group, r in list(ratio.items()):
        if not PLAUSIBLE_RATIO[0] <= r <= PLAUSIBLE_RATIO[1]:
            notes.append(f"{group} ratio {r:.2f} outside {PLAUSIBLE_RATIO}")
            del ratio[group]
    if "upperarm" in ratio and "forearm" in ratio:
        quotient = ratio["forearm"] / ratio["upperarm"]
        if not PLAUSIBLE_PROPORTION[0] <= quotient <= PLAUSIBLE_PROPORTION[1]:
            notes.append(
                f"forearm/upper arm proportion {quotient:.2f} x the template's "
                f"(outside {PLAUSIBLE_PROPORTION}; wrists misplaced?)"
            )
            del ratio["forearm"]
    return ratio, notes


def parts_start(
    fit,
    masks: torch.Tensor,
    images: torch.Tensor | None = None,
    parts_config: PartsOptions | None = None,
    iterations: int = 4,
) -> tuple[torch.Tensor, list[StartInfo]]:
    """The automatic initial guess for a batch (see the module docstring).

    Args:
        fit: the :class:`~torchfit.fit.SilhouetteFit` of the batch; it must use postures
            1 and 5.
        masks: (B, J, H, W) bool silhouettes, poses in ``fit.poses`` order.
        images: optional (B, J, 3, H, W) RGB in [0, 1] (the posture-5 image gives the wrists;
            without it the forearm keeps the overall scale).
        parts_config: part decomposition options.
        iterations: scale/root update rounds.

    Returns:
        ``(x, info)``: (B, P) start parameters within the fit's bounds and one
        :class:`StartInfo` per subject.

    Raises:
        ConfigError: postures 1 or 5 are not fitted.
    """
    from torchfit.parts.initial_guess import initial_guess_2d, posture_extents

    for j in (1, 5):
        if j not in fit.poses:
            raise ConfigError(
                f"fit.initial_guess: parts needs posture {j} in fit.poses (got {fit.poses})"
            )
    b = fit.batch
    if masks.shape[:2] != (b, len(fit.poses)):
        raise ConfigError(
            f"masks: expected (B={b}, J={len(fit.poses)}, H, W), got {tuple(masks.shape)}"
        )
    kw = fit.kw
    k1, k5 = fit.poses.index(1), fit.poses.index(5)
    x = fit.initial_params()
    rows = torch.arange(b, device=x.device)

    # ---- 2-D evidence per subject: extents of every posture, posture-5 joints
    extents = [[posture_extents(masks[i, k]) for k in range(len(fit.poses))] for i in range(b)]
    centres = torch.tensor(
        [[_centroid_u(masks[i, k].cpu().numpy()) for k in range(len(fit.poses))] for i in range(b)],
        **kw,
    )
    guesses = []
    for i in range(b):
        image5 = None
        if images is not None:
            image5 = (images[i, k5].permute(1, 2, 0).clamp(0, 1) * 255).round()
            image5 = image5.to(torch.uint8).cpu().numpy()
        guesses.append(initial_guess_2d(masks[i, k5], masks[i, k1], image5, parts_config))
    info = []
    for i in range(b):
        if extents[i][k1] is None:
            info.append(StartInfo("template", "posture 1: empty silhouette"))
        elif guesses[i].joints_pose5:
            info.append(StartInfo("parts"))
        else:
            info.append(StartInfo("parts_extents", guesses[i].message))
    use = torch.tensor([s.source != "template" for s in info], device=x.device)
    if not bool(use.any()):
        return x, info

    def obs(k: int, attr: str) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 2) pixels of an extents attribute and (B,) whether the pose has it."""
        have = torch.tensor([e[k] is not None for e in extents], device=x.device) & use
        vals = [getattr(e[k], attr) if e[k] is not None else np.zeros(2) for e in extents]
        return torch.as_tensor(np.stack(vals), **kw), have

    # ---- 1-2: floor translation per posture, overall scale from posture 1
    n_scale = fit.layout.num_scale_params
    scale = torch.ones(b, **kw)
    lo, hi = fit.lower, fit.upper
    feet_lost: list[set[int]] = [set() for _ in range(b)]
    for _ in range(iterations):
        for k, j in enumerate(fit.poses):
            head, have = obs(k, "head_top")
            foot, _ = obs(k, "lowest_foot")
            delta, ratio, feet_ok = _place(
                fit, x, j, rows, head, foot, centres[:, k], FOOT_TOLERANCE
            )
            for i in torch.nonzero(have & ~feet_ok).flatten().tolist():
                feet_lost[i].add(j)
            block = fit.layout.blocks[j]
            ctx, cty = block.root_column("tx"), block.root_column("ty")
            for col, d in ((ctx, delta[:, 0]), (cty, delta[:, 1])):
                new = (x[:, col] + d).clamp(lo[col], hi[col])
                x[:, col] = torch.where(have, new, x[:, col])
            if j == 1:
                scale = torch.where(have, scale * ratio, scale)
                s = scale[:, None].expand(-1, n_scale).clamp(lo[:n_scale], hi[:n_scale])
                x[:, :n_scale] = torch.where(have[:, None], s, x[:, :n_scale])
    for i, poses in enumerate(feet_lost):
        if 1 in poses:
            note = (
                "posture 1: the lowest silhouette pixel is not at the model's feet (feet lost "
                "or a shadow kept?): height from the head top alone"
            )
            info[i].message = f"{info[i].message}; {note}" if info[i].message else note
    for i in range(b):
        if bool(use[i]):
            info[i].scale = float(x[i, 0])

    # ---- 3: arm segment scales from the posture-5 joints
    template = fit.model.template
    _, origins = fit.pose_world(x, 5, rows)
    names = [f"{s}_{n}" for n in ("shoulder", "elbow", "wrist") for s in "lr"]
    model_px = fit.project(origins[:, [template.joints[n] for n in names]], rows)
    model_joint = {n: model_px[:, m] for m, n in enumerate(names)}
    for i in range(b):
        if info[i].source == "template":
            continue
        model_i = {n: p[i].cpu().numpy() for n, p in model_joint.items()}
        ratio, notes = arm_ratios(guesses[i].joints_pose5, model_i)
        if notes:
            note = "; ".join(notes) + ": kept the overall scale there"
            info[i].message = f"{info[i].message}; {note}" if info[i].message else note
        for group, r in ratio.items():
            col = fit.layout.scale_column(group, "z")
            if col is None:
                continue
            value = float(torch.clamp(x[i, col] * r, lo[col], hi[col]))
            x[i, col] = value
            setattr(info[i], group, value)
    return x, info
