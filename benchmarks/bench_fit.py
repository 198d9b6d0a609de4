"""Speed of the six-posture fit: autograd LM against the paper's numeric MINPACK baseline, and
batch throughput.

    python benchmarks/bench_fit.py --data DIR [--config configs/benchmark.yaml]
        [--baseline-subjects 1] [--batch-sizes 1,4,16] [--threads N]

Part 1 (same subject, same residual, same stopping rule, one run): one stage over every
scale and the root poses of the six postures, from the template start, solved (a) by the
batched LM with the structured autograd Jacobian and (b) by MINPACK lmdif with forward
differences on the rendered-contour residual (torchfit.fit.baseline). Both final costs are
evaluated with the rendered residual, so they compare one to one.

Part 2: wall time of the whole configured fit (segmentation included) for B subjects in one
batch, for each B; subjects are taken from DIR in order (repeated if DIR has fewer).

Prints a markdown table, the machine and the versions.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchfit.body.model import BodyModel  # noqa: E402
from torchfit.camera import stack_cameras  # noqa: E402
from torchfit.config import load_config, replace_keys  # noqa: E402
from torchfit.fit import SilhouetteFit, StageOptions, solve_stage  # noqa: E402
from torchfit.fit.baseline import minpack_stage, rendered_residual  # noqa: E402
from torchfit.io.dataset import load_dataset  # noqa: E402
from torchfit.pipeline import person_data, run, segment_subject  # noqa: E402
from torchfit.solver import LMOptions  # noqa: E402


def machine() -> str:
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__} ({torch.get_num_threads()} threads), "
        f"python {platform.python_version()}"
    )


def part1(config, subjects, max_iter: int, lm_factor: int = 4) -> None:
    model = BodyModel(config.model.template)
    segmented = [segment_subject(s, config) for s in subjects]
    person = person_data(
        config,
        torch.stack([m for _, m, _ in segmented]),
        torch.stack([sh for _, _, sh in segmented]),
        stack_cameras([s.camera for s in subjects]),
        torch.float64,
    )
    fit = SilhouetteFit(
        model, person, config.fit, (config.model.scale_min, config.model.scale_max)
    )
    stage = StageOptions(name="scales_and_root", scales=["all"], joints=False, root=True)
    options = LMOptions(
        max_iter=max_iter, ftol=config.solver.ftol, xtol=config.solver.xtol, gtol=config.solver.gtol
    )
    x0 = fit.initial_params()
    start_cost = 0.5 * (rendered_residual(fit, x0) ** 2).sum(1)
    t = time.perf_counter()
    x_mp, res_mp = minpack_stage(fit, x0, stage, options)
    t_mp = time.perf_counter() - t
    cost_mp = 0.5 * (rendered_residual(fit, x_mp) ** 2).sum(1)
    # the LM with a longer budget; its trajectory gives the time to reach MINPACK's cost
    free = fit.stage_indices(stage.scales, stage.joints, stage.root)
    track: list[tuple[float, torch.Tensor]] = []
    t = time.perf_counter()

    def record(it) -> None:
        track.append((time.perf_counter() - t, it.x.clone()))

    lm_options = LMOptions(
        max_iter=lm_factor * max_iter, ftol=options.ftol, xtol=options.xtol, gtol=options.gtol
    )
    x_lm, res = solve_stage(fit, x0, stage, lm_options, callback=record)
    t_lm = time.perf_counter() - t
    cost_lm = 0.5 * (rendered_residual(fit, x_lm) ** 2).sum(1)
    reach = [None] * len(subjects)
    for elapsed, x_free in track:  # rendered cost along the LM trajectory
        x_full = x0.clone()
        x_full[:, free] = x_free
        cost = 0.5 * (rendered_residual(fit, x_full) ** 2).sum(1)
        for i in range(len(subjects)):
            if reach[i] is None and float(cost[i]) <= float(cost_mp[i]):
                reach[i] = elapsed
    n_free = free.numel()
    print(
        f"\n## Autograd LM vs numeric MINPACK baseline ({len(subjects)} subject(s), "
        f"{n_free} free parameters; MINPACK max_iter {max_iter}, LM "
        f"max_iter {lm_factor * max_iter})\n"
    )
    print(
        "| subject | start cost | MINPACK cost | MINPACK s | LM final cost | LM s total | "
        "LM s to MINPACK's cost | speed-up to equal cost |"
    )
    print("|---|---|---|---|---|---|---|---|")
    per_mp = t_mp / len(subjects)  # MINPACK runs subject by subject
    for i, s in enumerate(subjects):
        to_equal = reach[i]
        ratio = f"{per_mp / to_equal:.1f}x" if to_equal else "not reached"
        reached = f"{to_equal:.1f}" if to_equal else "-"
        print(
            f"| {s.name} | {float(start_cost[i]):.1f} | {float(cost_mp[i]):.1f} | "
            f"{per_mp:.1f} | {float(cost_lm[i]):.1f} | {t_lm / len(subjects):.1f} | "
            f"{reached} | {ratio} |"
        )
    print(
        f"\nLM iterations {res.n_iter.tolist()}, MINPACK evaluations "
        f"{[int(r.nfev[0]) for r in res_mp]}; costs are the rendered-contour residual at "
        "each point; LM times include its own residual and Jacobian work only (the "
        "rendered costs along its trajectory are computed afterwards)."
    )


def part2(config, root: Path, names: list[str], batch_sizes: list[int]) -> None:
    print("\n## Whole fit, batch throughput (segmentation + all stages + outputs)\n")
    print("| B | wall s | s per subject | subjects per minute | statuses |")
    print("|---|---|---|---|---|")
    for b in batch_sizes:
        with tempfile.TemporaryDirectory() as tmp:
            data = Path(tmp) / "data"
            data.mkdir()
            for i in range(b):
                src = root / names[i % len(names)]
                os.symlink(src, data / f"{i:03d}_{src.name}")
            cfg = replace_keys(
                config,
                {
                    "data.root": str(data),
                    "data.subjects": None,
                    "run.out": str(Path(tmp) / "run"),
                    "run.resume": False,
                    "fit.batch_size": b,
                    "output.tensorboard": False,
                },
            )
            t = time.perf_counter()
            results = run(cfg, Path(cfg.run.out))
            wall = time.perf_counter() - t
            statuses = sorted({r.status for r in results})
            print(f"| {b} | {wall:.0f} | {wall / b:.1f} | {60 * b / wall:.2f} | {statuses} |")
            shutil.rmtree(Path(tmp) / "run", ignore_errors=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--config", type=Path, default=Path("configs/benchmark.yaml"))
    parser.add_argument("--baseline-subjects", type=int, default=1)
    parser.add_argument("--baseline-max-iter", type=int, default=20)
    parser.add_argument("--batch-sizes", default="1,4,16")
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--skip-baseline", action="store_true")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    config = load_config(args.config, args.set)
    subjects = [s for s in load_dataset(args.data) if s.ok]
    print(f"# bench_fit on {args.data} ({machine()})" + "".join(f" --set {o}" for o in args.set))
    if not args.skip_baseline:
        part1(config, subjects[: args.baseline_subjects], args.baseline_max_iter)
    sizes = [int(b) for b in args.batch_sizes.split(",") if b]
    part2(config, args.data, [s.name for s in subjects], sizes)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
