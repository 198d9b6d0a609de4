"""Throughput of the fit on one device (a GPU or the CPU), and where its time goes.

    python benchmarks/bench_device.py --data DIR [--config configs/benchmark.yaml]
        [--device cuda] [--dtype float32] [--batch-sizes 1,16,64,256] [--budget-s 600]
        [--short N] [--parts-batch 64] [--profile-batch 64] [--measurements FILE]
        [--set KEY=VALUE ...]

1. Every subject of DIR is read and segmented once, on the CPU, as ``tools/fit.py`` does
   (timed: the segmentation's seconds per subject, reported separately).
2. A warm-up fit of two iterations per stage at B = 2 (CUDA context, kernels, caches).
3. For each B, a batch cycling through the segmented subjects is fitted on the device: the
   initial guess, every stage of the config and the measurements (outputs are not written).
   Subjects per hour = 3600 B / seconds. A B whose predicted time would overrun
   ``--budget-s`` is skipped and said so: the prediction is the line through the last two
   batches' times (a fixed part and a part per subject), or after one batch its time per
   subject times B (an overestimate, since batching pays). ``--short N`` gives every stage
   of the config at most N iterations, to see how a batch scales in little time.
4. ``--parts-batch``: the same fit once more with the parts timed (the device synchronised
   around each): the contour choice (posing every vertex, then on the CPU: drawing the
   silhouette edges, outline, k-d tree), the Jacobian with its residual, the trial residuals,
   the initial guess, and the rest of the solver (normal equations, Cholesky, bookkeeping).
5. ``--profile-batch``: ``torch.profiler`` over a short fit (two iterations per stage): the
   operators that take the most device and host time.

``--measurements FILE``: the measurements of each distinct subject (from the first B that
holds them all) as JSON, to compare devices and dtypes.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import importlib
import json
import platform
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchfit.body.measure import measure_model  # noqa: E402
from torchfit.body.model import BodyModel  # noqa: E402
from torchfit.config import load_config, replace_keys  # noqa: E402
from torchfit.fit import SilhouetteFit  # noqa: E402
from torchfit.io.dataset import load_dataset  # noqa: E402
from torchfit.pipeline.prepare import prepare_subject  # noqa: E402
from torchfit.pipeline.runtime import apply_runtime, torch_dtype  # noqa: E402

#: the module ``torchfit.pipeline.run`` (the package exports a function of that name)
run_module = importlib.import_module("torchfit.pipeline.run")


def predict(history: list[tuple[int, float]], b: int) -> float:
    """Seconds for a batch of ``b`` from the (B, seconds) of the batches before it."""
    if len(history) >= 2 and history[-1][0] != history[-2][0]:
        (b0, s0), (b1, s1) = history[-2:]
        per = max(0.0, (s1 - s0) / (b1 - b0))
        return max(s1, s1 + per * (b - b1))
    b1, s1 = history[-1]
    return s1 / b1 * b


def shortened(config, n: int):
    """``config`` with every stage limited to ``n`` iterations."""
    stages = [dataclasses.replace(st, max_iter=n) for st in config.fit.stages]
    return replace_keys(config, {"fit.stages": stages})


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def fit_once(prepared, model, config, device) -> tuple[float, dict, list]:
    """Fit ``prepared`` as one batch; (seconds, measurements (name -> (B,) tensor), records)."""
    sync(device)
    t = time.perf_counter()
    fit, x, _, records = run_module._fit(prepared, model, config)
    scales = model.expand_scales(fit.layout.group_scales(x))
    measures = {k: v.detach().cpu() for k, v in measure_model(model, scales).items()}
    sync(device)
    return time.perf_counter() - t, measures, records


class PartTimer:
    """Wall time of named calls, outermost calls only, the device synchronised around each."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self.depth = 0
        self.undo: list = []

    def wrap(self, owner, attr: str, name: str) -> None:
        original = getattr(owner, attr)

        @functools.wraps(original)
        def timed(*args, **kwargs):
            if self.depth:
                return original(*args, **kwargs)
            self.depth += 1
            sync(self.device)
            t = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                sync(self.device)
                self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t
                self.calls[name] = self.calls.get(name, 0) + 1
                self.depth -= 1

        self.undo.append((owner, attr, original))
        setattr(owner, attr, timed)

    def restore(self) -> None:
        for owner, attr, original in reversed(self.undo):
            setattr(owner, attr, original)


def parts(prepared, model, config, device) -> None:
    timer = PartTimer(device)
    timer.wrap(run_module, "start_params", "initial guess")
    for cls in {type_ for type_ in SilhouetteFit.__subclasses__()} | {SilhouetteFit}:
        for attr, name in (
            ("select", "contour choice"),
            ("jacobian_and_residual", "Jacobian and residual"),
            ("residual", "trial residuals"),
        ):
            if attr in vars(cls):
                timer.wrap(cls, attr, name)
    try:
        total, _, _ = fit_once(prepared, model, config, device)
    finally:
        timer.restore()
    b = len(prepared)
    print(f"\n## Where the time goes, B = {b} ({total:.1f} s, {3600 * b / total:.0f} subjects/h)\n")
    print("| part | calls | s | share | ms per call |")
    print("|---|---|---|---|---|")
    rest = total - sum(timer.seconds.values())
    for name, s in [*timer.seconds.items(), ("solver and the rest", rest)]:
        calls = timer.calls.get(name, 0)
        per = f"{1e3 * s / calls:.1f}" if calls else ""
        print(f"| {name} | {calls or ''} | {s:.1f} | {100 * s / total:.0f} % | {per} |")
    print(
        "\nThe device is synchronised around each timed call (the pipeline's own host copies "
        "already synchronise it once per contour choice), so the parts add up to the total."
    )


def profile(prepared, model, config, device, rows: int = 20) -> None:
    activities = [torch.profiler.ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=activities) as prof:
        fit_once(prepared, model, config, device)
    key = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    print(f"\n## torch.profiler, B = {len(prepared)}, two iterations per stage, by {key}\n")
    print("```")
    print(prof.key_averages().table(sort_by=key, row_limit=rows))
    print("```")
    if device.type == "cuda":
        print("\nBy host time:\n\n```")
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows))
        print("```")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--config", type=Path, default=Path("configs/benchmark.yaml"))
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    parser.add_argument("--batch-sizes", default="1,16,64,256")
    parser.add_argument("--budget-s", type=float, default=600.0)
    parser.add_argument("--short", type=int, default=0, metavar="N")
    parser.add_argument("--parts-batch", type=int, default=0)
    parser.add_argument("--profile-batch", type=int, default=0)
    parser.add_argument("--measurements", type=Path)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    begun = time.perf_counter()
    sets = [*args.set, f"run.device={args.device}", f"run.dtype={args.dtype}"]
    config = load_config(args.config, sets)
    if args.short:
        config = shortened(config, args.short)
    short = shortened(config, 2)
    apply_runtime(config.run)
    device = torch.device(args.device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor()
    print(
        f"# bench_device on {args.data}: {name}, torch {torch.__version__}, "
        f"{torch.get_num_threads()} CPU threads, {args.dtype}"
        + "".join(f" --set {s}" for s in args.set)
    )
    subjects = [s for s in load_dataset(args.data) if s.ok]
    t = time.perf_counter()
    prepared = [prepare_subject(s, config) for s in subjects]
    seg = (time.perf_counter() - t) / len(prepared)
    print(
        f"\nSegmentation (CPU, {len(prepared)} subjects, reading included): {seg:.2f} s per "
        f"subject, {3600 / seg:.0f} subjects/h on one process."
    )
    model = BodyModel(config.model.template, device=device, dtype=torch_dtype(args.dtype))
    cycle = lambda b: [prepared[i % len(prepared)] for i in range(b)]  # noqa: E731
    t = time.perf_counter()
    fit_once(cycle(2), model, short, device)
    print(f"Warm-up (B = 2, two iterations per stage): {time.perf_counter() - t:.1f} s.")

    print("\n## The fit on the device (initial guess, all stages, measurements)\n")
    print(
        "| B | s | s per subject | subjects per hour | peak device memory, GB "
        "| iterations per subject |"
    )
    print("|---|---|---|---|---|---|")
    history: list[tuple[int, float]] = []
    saved = None
    for b in [int(v) for v in args.batch_sizes.split(",") if v]:
        left = args.budget_s - (time.perf_counter() - begun)
        if history and predict(history, b) > left:
            print(
                f"| {b} | skipped: about {predict(history, b):.0f} s predicted, {left:.0f} s left |"
            )
            continue
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        s, measures, records = fit_once(cycle(b), model, config, device)
        history.append((b, s))
        peak = torch.cuda.max_memory_allocated(device) / 1e9 if device.type == "cuda" else 0.0
        iters = sum(sum(r.iterations for r in rec) for rec in records) / b
        print(
            f"| {b} | {s:.1f} | {s / b:.2f} | {3600 * b / s:.0f} | {peak:.2f} | {iters:.1f} |",
            flush=True,
        )
        if saved is None and b >= len(prepared):
            saved = {
                p.subject.name: {k: float(v[i]) for k, v in measures.items()}
                for i, p in enumerate(prepared)
            }
    if args.measurements and saved is not None:
        args.measurements.write_text(json.dumps(saved, indent=1))
    if args.parts_batch:
        parts(cycle(args.parts_batch), model, config, device)
    if args.profile_batch:
        profile(cycle(args.profile_batch), model, short, device)
    print(f"\nWhole benchmark: {time.perf_counter() - begun:.0f} s.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
