"""A hopeless subject in a batch costs its own time only (the solver's active set).

    python benchmarks/bench_active_set.py [--data data/demo] [--subject subject_001]
        [--max-iter 10] [--ftol 0.05] [--repeats 3] [--threads N]

One stage over every scale and the root poses of the six postures (the configured solver
options, ``--ftol`` loosened so that the real subject converges within ``--max-iter``), from
the template start, solved for (a) the real subject alone, (b) a hopeless subject alone (the
real subject's camera, every silhouette one huge ellipse that no body can fill; it runs to
``--max-iter``) and (c) both in one batch. With the active set compacted, (c) takes about
(a) + (b): once the real subject has converged, only the hopeless one is evaluated. The real
subject's result in (c) is checked to equal (a) bit for bit. Prints the median wall time of
``--repeats`` runs, the iterations, the machine and the versions.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchfit.body.model import BodyModel  # noqa: E402
from torchfit.camera import stack_cameras  # noqa: E402
from torchfit.config import load_config  # noqa: E402
from torchfit.fit import SilhouetteFit, StageOptions, solve_stage  # noqa: E402
from torchfit.io.dataset import load_subject  # noqa: E402
from torchfit.pipeline import person_data, segment_subject  # noqa: E402


def hopeless_masks(masks: torch.Tensor) -> torch.Tensor:
    """(J, H, W) silhouettes replaced by one ellipse over most of the image."""
    _, h, w = masks.shape
    blob = np.zeros((h, w), np.uint8)
    cv2.ellipse(blob, (w // 2, h // 2), (int(w * 0.45), int(h * 0.45)), 0, 0, 360, 255, -1)
    return torch.from_numpy(blob > 0).expand_as(masks).clone()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/demo.yaml")
    ap.add_argument("--data", default="data/demo")
    ap.add_argument("--subject", default="subject_001")
    ap.add_argument("--max-iter", type=int, default=10)
    ap.add_argument("--ftol", type=float, default=0.05)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    config = load_config(args.config)
    model = BodyModel(config.model.template, dtype=torch.float64)
    subject = load_subject(Path(args.data) / args.subject)
    _, masks, shadow = segment_subject(subject, config.segmentation)
    used = [j - 1 for j in config.fit.poses]
    real = (masks[used], shadow[used])
    bad = (hopeless_masks(masks[used]), torch.zeros_like(shadow[used]))
    stage = StageOptions(name="bench", scales=("all",), joints=False, root=True)
    options = config.solver.lm_options(args.max_iter)
    options = dataclasses.replace(options, ftol=args.ftol)

    def solve(items):
        person = person_data(
            config,
            torch.stack([m for m, _ in items]),
            torch.stack([s for _, s in items]),
            stack_cameras([subject.camera] * len(items)),
            model.dtype,
        )
        fit = SilhouetteFit(model, person, config.fit)
        t0 = time.perf_counter()
        x, res = solve_stage(fit, fit.initial_params(), stage, options)
        return time.perf_counter() - t0, x, res

    runs = {"real alone": [real], "hopeless alone": [bad], "real + hopeless": [real, bad]}
    rows = []
    out = {}
    for name, items in runs.items():
        times = []
        for _ in range(args.repeats):
            seconds, x, res = solve(items)
            times.append(seconds)
        out[name] = (x, res)
        iters = ", ".join(str(int(n)) for n in res.n_iter)
        status = ", ".join(s.name for s in res.statuses)
        rows.append(f"| {name} | {statistics.median(times):.1f} | {iters} | {status} |")
    same = torch.equal(out["real + hopeless"][0][0], out["real alone"][0][0])
    print(
        f"subject {args.subject}, one stage (all scales + root), max_iter {args.max_iter}, "
        f"ftol {args.ftol}, median of {args.repeats}"
    )
    print("| run | seconds | iterations | status |\n|---|---|---|---|")
    print("\n".join(rows))
    print(f"real subject's parameters in the batch equal alone: {same}")
    print(
        f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads, "
        f"torch {torch.__version__}, python {platform.python_version()}"
    )


if __name__ == "__main__":
    main()
