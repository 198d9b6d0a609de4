"""Time the parts of one LM iteration of the fit: the contour choice, the residual, the
Jacobian (with its residual) and the normal equations (dense and by posture blocks).

    python benchmarks/bench_fit_parts.py --data DIR [--config configs/benchmark.yaml]
        [--batch-sizes 1,16] [--repeats 7] [--threads 1]

Subjects are the first four of DIR (repeated to fill a batch), segmented as the config says,
at the template start perturbed by 2 % (seeded); every part is timed ``--repeats`` times after
a warm-up and the median is printed, in milliseconds per batch and per subject.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_fit import fit_problem  # noqa: E402

from torchfit.config import load_config  # noqa: E402
from torchfit.io.dataset import load_dataset  # noqa: E402
from torchfit.solver.normal import normal_equations, valid_entries  # noqa: E402


def median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def parts(config, subjects, batch: int, repeats: int) -> dict[str, float]:
    fit = fit_problem(config, [subjects[i % len(subjects)] for i in range(batch)])
    g = torch.Generator().manual_seed(0)
    x = fit.initial_params()
    x = x + 0.02 * torch.randn(x.shape, generator=g, dtype=x.dtype)
    free = fit.stage_indices(["all"], True, True)
    sel = fit.select(x)
    jac, r = fit.jacobian_and_residual(x, free, sel)
    valid = valid_entries(fit.residual_mask(), batch)
    blocks = fit.jacobian_blocks(free)
    return {
        "contour choice": median_ms(lambda: fit.select(x), repeats),
        "residual": median_ms(lambda: fit.residual(x, sel), repeats),
        "Jacobian and residual": median_ms(
            lambda: fit.jacobian_and_residual(x, free, sel), repeats
        ),
        "JᵀJ, Jᵀr dense": median_ms(lambda: normal_equations(jac, r, valid), repeats),
        "JᵀJ, Jᵀr by blocks": median_ms(lambda: normal_equations(jac, r, valid, blocks), repeats),
        "M x F": f"{jac.shape[1]} x {jac.shape[2]}",
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--config", type=Path, default=Path("configs/benchmark.yaml"))
    parser.add_argument("--batch-sizes", default="1,16")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = load_config(args.config)
    subjects = [s for s in load_dataset(args.data) if s.ok][:4]
    print(f"# fit parts on {args.data}, {args.threads} thread(s), torch {torch.__version__}")
    print("\n| B | part | ms per batch | ms per subject |\n|---|---|---|---|")
    for b in [int(v) for v in args.batch_sizes.split(",") if v]:
        for name, value in parts(config, subjects, b, args.repeats).items():
            if isinstance(value, str):
                print(f"| {b} | {name} | {value} | |")
            else:
                print(f"| {b} | {name} | {value:.1f} | {value / b:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
