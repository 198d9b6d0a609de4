"""What the automatic initial guess changes: the fit from the template start against the fit
from the parts start (``fit.initial_guess: parts``), same subjects, same stages, one run.

    python benchmarks/bench_initial_guess.py --data DIR [--config configs/benchmark.yaml]
        [--subjects N] [--threads N] [--csv FILE]

Each batch of ``fit.batch_size`` subjects is segmented once; then both starts run the
configured stages. Per start it reports the error of the start itself and of the fitted
measurements against truth.json, the share of subjects fitted to the right answer (height,
arm span and lower leg all within the first paper's Table 1 errors: 2.1 %, 1.6 %, 7.6 %), the
share that reach the lower final cost of the two (within 1 %), iterations per stage, and wall
time. Prints a markdown table, the machine and the versions.
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchfit.body.measure import measure_model  # noqa: E402
from torchfit.body.model import BodyModel  # noqa: E402
from torchfit.camera import stack_cameras  # noqa: E402
from torchfit.config import load_config  # noqa: E402
from torchfit.errors import TorchfitError  # noqa: E402
from torchfit.fit import SilhouetteFit, solve_stage  # noqa: E402
from torchfit.fit.initial_guess import parts_start  # noqa: E402
from torchfit.io.dataset import load_dataset  # noqa: E402
from torchfit.pipeline import person_data, segment_subject  # noqa: E402

KEYS = ("height", "arm_span", "lower_leg", "thigh", "upper_arm", "forearm", "shoulder_width")
#: The first paper's Table 1 mean errors: a fit within all three found the right answer.
RIGHT = {"height": 2.1, "arm_span": 1.6, "lower_leg": 7.6}
STARTS = ("template", "parts")


def machine() -> str:
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__} ({torch.get_num_threads()} threads), "
        f"python {platform.python_version()}"
    )


def errors_pct(model, x, fit, truth: list[dict]) -> list[dict[str, float]]:
    groups = fit.layout.group_scales(x)
    m = measure_model(model, model.expand_scales(groups))
    return [
        {k: 100.0 * (float(m[f"{k}_m"][i]) / t[f"{k}_m"] - 1.0) for k in KEYS}
        for i, t in enumerate(truth)
    ]


def fit_from(fit, x, config):
    """Run the configured stages; per subject: iterations by stage, the cost after every
    iteration (all stages), the final cost; and the wall time."""
    t0 = time.perf_counter()
    iters = [[] for _ in range(fit.batch)]
    trace = [[] for _ in range(fit.batch)]

    def record(it) -> None:
        for i in range(fit.batch):
            if int(it.status[i]) == 0 or not trace[i] or trace[i][-1] != float(it.cost[i]):
                trace[i].append(float(it.cost[i]))

    for stage in config.fit.stages:
        options = config.solver.lm_options(stage.max_iter or config.solver.max_iter)
        n_before = [len(t) for t in trace]
        x, res = solve_stage(fit, x, stage, options, callback=record)
        for i in range(fit.batch):
            iters[i].append(int(res.n_iter[i]))
            del trace[i][n_before[i] + int(res.n_iter[i]) :]  # iterations after it stopped
    cost = [t[-1] if t else float("nan") for t in trace]
    return x, iters, trace, cost, time.perf_counter() - t0


def iterations_to(trace: list[float], target: float) -> int | None:
    """First iteration (1-based, stages concatenated) whose cost is <= target; None if none."""
    for k, c in enumerate(trace):
        if c <= target:
            return k + 1
    return None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path)
    ap.add_argument("--config", default="configs/benchmark.yaml")
    ap.add_argument("--subjects", type=int, default=None, help="first N subjects only")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--csv", type=Path, default=None, help="per-subject rows")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    config = load_config(args.config)
    subjects = load_dataset(args.data)[: args.subjects]
    dtype = torch.float64 if config.run.dtype == "float64" else torch.float32
    model = BodyModel(config.model.template, dtype=dtype)
    rows: list[dict] = []
    seconds = {s: 0.0 for s in STARTS}
    size = config.fit.batch_size
    for b0 in range(0, len(subjects), size):
        batch, masks, shadows, images, truth = [], [], [], [], []
        for s in subjects[b0 : b0 + size]:
            if s.truth is None:
                print(f"{s.name}: skipped (no truth.json)", file=sys.stderr)
                continue
            try:
                img, mask, shadow = segment_subject(s, config)
            except (TorchfitError, OSError) as exc:
                print(f"{s.name}: skipped ({exc})", file=sys.stderr)
                continue
            batch.append(s)
            masks.append(mask)
            shadows.append(shadow)
            images.append(img)
            truth.append(s.truth)
        if not batch:
            continue
        masks_t = torch.stack(masks)
        person = person_data(
            config, masks_t, torch.stack(shadows), stack_cameras([s.camera for s in batch]), dtype
        )
        fit = SilhouetteFit(
            model, person, config.fit, (config.model.scale_min, config.model.scale_max)
        )
        t0 = time.perf_counter()
        x_parts, info = parts_start(fit, masks_t, torch.stack(images), config.parts)
        guess_s = time.perf_counter() - t0
        starts = {"template": fit.initial_params(), "parts": x_parts}
        out = {}
        for name, x0 in starts.items():
            x, iters, trace, cost, sec = fit_from(fit, x0, config)
            seconds[name] += sec + (guess_s if name == "parts" else 0.0)
            out[name] = (errors_pct(model, x0, fit, truth), errors_pct(model, x, fit, truth))
            out[name] += (iters, trace, cost)
        for i, s in enumerate(batch):
            row = {"subject": s.name, "parts_source": info[i].source}
            # the cost the template start ends at: how soon does each start get there?
            target = 1.01 * out["template"][4][i]
            for name in STARTS:
                start_err, end_err, iters, trace, cost = out[name]
                row[f"{name}_iters"] = sum(iters[i])
                row[f"{name}_iters_to_template_cost"] = iterations_to(trace[i], target)
                row[f"{name}_iters_by_stage"] = "+".join(map(str, iters[i]))
                row[f"{name}_cost"] = cost[i]
                for k in KEYS:
                    row[f"{name}_start_{k}"] = start_err[i][k]
                    row[f"{name}_{k}"] = end_err[i][k]
            rows.append(row)
            print(
                f"{s.name}: "
                + "  ".join(
                    f"{n}: h {row[f'{n}_height']:+.1f}% span {row[f'{n}_arm_span']:+.1f}% "
                    f"it {row[f'{n}_iters_by_stage']}"
                    for n in STARTS
                ),
                flush=True,
            )
    if not rows:
        print("no subject could be segmented", file=sys.stderr)
        return 1
    if args.csv:
        with args.csv.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)

    n = len(rows)

    def mean(values) -> float:
        values = list(values)
        return sum(values) / len(values)

    print(f"\n{n} subjects from {args.data}, config {args.config}; {machine()}\n")
    print("| | template start | parts start |")
    print("|---|---|---|")
    for k in ("height", "arm_span", "upper_arm", "forearm"):
        cells = [f"{mean(abs(r[f'{s}_start_{k}']) for r in rows):.1f} %" for s in STARTS]
        print(f"| start error, {k} (mean abs) | " + " | ".join(cells) + " |")
    right = {
        s: sum(all(abs(r[f"{s}_{k}"]) < v for k, v in RIGHT.items()) for r in rows) for s in STARTS
    }
    print(
        "| right answer (height, arm span, lower leg within Table 1) | "
        + " | ".join(f"{right[s]}/{n} ({100 * right[s] / n:.0f} %)" for s in STARTS)
        + " |"
    )
    best = {
        s: sum(r[f"{s}_cost"] <= 1.01 * min(r[f"{t}_cost"] for t in STARTS) for r in rows)
        for s in STARTS
    }
    print(
        "| reaches the lower final cost of the two (1 %) | "
        + " | ".join(f"{best[s]}/{n}" for s in STARTS)
        + " |"
    )
    cells = []
    for s in STARTS:
        got = sorted(v for r in rows if (v := r[f"{s}_iters_to_template_cost"]) is not None)
        median = got[len(got) // 2] if got else "-"
        cells.append(f"{len(got)}/{n} subjects, median iteration {median}")
    print("| reaches the template start's final cost (+1 %) | " + " | ".join(cells) + " |")
    n_stage = len(rows[0]["template_iters_by_stage"].split("+"))
    for si in range(n_stage):
        cells = [
            f"{mean(int(r[f'{s}_iters_by_stage'].split('+')[si]) for r in rows):.1f}"
            for s in STARTS
        ]
        print(f"| iterations, stage {si + 1} (mean) | " + " | ".join(cells) + " |")
    print(
        "| iterations, total (mean) | "
        + " | ".join(f"{mean(r[f'{s}_iters'] for r in rows):.1f}" for s in STARTS)
        + " |"
    )
    for k in KEYS:
        cells = [f"{mean(abs(r[f'{s}_{k}']) for r in rows):.2f} %" for s in STARTS]
        print(f"| fitted {k}, mean abs error | " + " | ".join(cells) + " |")
    print(
        "| fit wall time per subject | "
        + " | ".join(f"{seconds[s] / n:.1f} s" for s in STARTS)
        + " |"
    )
    sources = {}
    for r in rows:
        sources[r["parts_source"]] = sources.get(r["parts_source"], 0) + 1
    print(f"\nparts start sources: {sources}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
