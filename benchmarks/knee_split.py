"""Where the knee sits: does the fit find the thigh / calf split that the silhouettes show?

Each body is the template itself with its thighs and calves rescaled along their length
(``--splits``). It is drawn as exact silhouettes by the fit's own rasteriser, in the six
postures at their nominal angles, through a nominal camera. So there is no segmentation and no
model mismatch: the true parameters explain the silhouettes up to the pixel grid.

Each body is fitted twice with the config's problem and stages:
- from the template's start (unit scales, as every fit starts);
- from the true split (the template's start with the true ``thigh:z`` and ``calf:z``).

It prints, per body, the true thigh and lower leg, each fit's and its final cost. It also
prints the cost at the true parameters themselves. A fit that finds the knee comes back near
the truth from either start; one that does not keeps the split it started from.

    python benchmarks/knee_split.py --config configs/benchmark.yaml
"""

from __future__ import annotations

import argparse
import math

import torch

from torchfit.body.measure import measure_model
from torchfit.body.model import BodyModel
from torchfit.body.postures import POSTURES, pose_nominal
from torchfit.camera import camera_centre, project_points, stack_cameras
from torchfit.config.loader import load_config
from torchfit.pipeline.prepare import person_data
from torchfit.pipeline.run import build_problem
from torchfit.pipeline.stages import run_stages
from torchfit.viz.preview import nominal_view
from torchfit.viz.raster import render_silhouette


def _splits(text: str) -> list[tuple[float, float]]:
    out = []
    for item in text.split(","):
        thigh, calf = (float(v) for v in item.split(":"))
        out.append((thigh, calf))
    return out


def _scales(model: BodyModel, thigh: float, calf: float) -> torch.Tensor:
    segments = model.template.segments
    scales = torch.ones(1, model.num_segments, 3, dtype=model.dtype)
    for name, value in (("thigh", thigh), ("calf", calf)):
        for side in ("l", "r"):
            scales[0, segments.index(f"{side}_{name}"), 2] = value
    return scales


def _silhouettes(model: BodyModel, camera, scales: torch.Tensor) -> torch.Tensor:
    """(6, H, W) exact silhouettes of the body in the nominal postures (the fit's rasteriser)."""
    w, h = camera.image_size
    faces = model.faces.cpu().numpy()
    masks = []
    for posture in POSTURES:
        _, out = pose_nominal(model, scales, posture, camera_centre(camera.R, camera.t))
        px = project_points(out.vertices, camera.to(dtype=out.vertices.dtype))[0].numpy()
        masks.append(torch.from_numpy(render_silhouette(px, faces, (w, h)) > 127))
    return torch.stack(masks)


def _cost(fit, x: torch.Tensor) -> float:
    """The least-squares cost ½|r|² (no robust loss) of one parameter row."""
    r = fit.residual(x)
    return 0.5 * float((r[0] ** 2).sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/benchmark.yaml")
    parser.add_argument(
        "--splits",
        default="0.93:1.05,1.06:0.95,0.93:1.0,1.0:1.0",
        help="bodies as thigh:calf length scales, comma-separated",
    )
    parser.add_argument("--azimuth-deg", type=float, default=20.0)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = load_config(args.config)
    model = BodyModel(config.model.template)
    camera = nominal_view(azimuth_deg=args.azimuth_deg)
    used = [j - 1 for j in config.fit.poses]
    print(f"config {args.config}; prior weight {config.fit.prior.weight}")
    header = "thigh:z calf:z | true thigh, lower leg | from template: thigh, lower leg, cost | "
    print(header + "from the true split: thigh, lower leg, cost | cost at the truth")
    for thigh, calf in _splits(args.splits):
        scales = _scales(model, thigh, calf)
        truth = {k: float(v[0]) for k, v in measure_model(model, scales).items()}
        masks = _silhouettes(model, camera, scales)[used][None]
        shadow = torch.zeros_like(masks)
        person = person_data(config, masks, shadow, stack_cameras([camera]), model.dtype)
        fit = build_problem(model, person, config, [{}])
        start = fit.initial_params()
        true_start = start.clone()
        for group, value in (("thigh", thigh), ("calf", calf)):
            true_start[:, fit.layout.scale_column(group, "z")] = value
        row = [f"{thigh:.3f} {calf:.3f}", f"{truth['thigh_m']:.4f} {truth['lower_leg_m']:.4f}"]
        for x0 in (start, true_start):
            x, _ = run_stages(fit, x0, config, ["body"])
            m = measure_model(model, model.expand_scales(fit.layout.group_scales(x)))
            row.append(
                f"{float(m['thigh_m'][0]):.4f} {float(m['lower_leg_m'][0]):.4f} {_cost(fit, x):.3f}"
            )
        at_truth = _cost(fit, true_start)
        row.append(f"{at_truth:.3f}" if math.isfinite(at_truth) else "nan")
        print(" | ".join(row))


if __name__ == "__main__":
    main()
