"""Throughput of the batched LM against a loop of scipy's MINPACK LM, on one NIST problem.

For each batch size B, B copies of a NIST StRD problem are solved from Start 2 jittered by a
uniform +-10 % per parameter (seeded). ``torchfit`` solves them in one batch with
``levenberg_marquardt`` (autograd Jacobian); the baseline loops over them with
``scipy.optimize.least_squares(method="lm")`` on a NumPy residual (MINPACK's lmdif). Both use
the same tolerances. Every case runs in a fresh subprocess so that its peak resident set size
(``resource.getrusage(RUSAGE_SELF).ru_maxrss``, which includes Python, torch and the data) is
its own; times are the median of ``--repeats`` runs inside that process, after one untimed
warm-up run (first-call imports and allocations).

    python benchmarks/bench_solver.py --threads 1
    python benchmarks/bench_solver.py --threads 1 --keep-heap   # glibc malloc keeps its heap

``--keep-heap`` calls :func:`torchfit.solver.keep_heap` at the start of every case (torchfit
and scipy alike): glibc's mmap threshold fixed at 16 MiB and its trim threshold at 64 MiB, so
blocks up to 16 MiB come from the heap and the heap is not handed back to the kernel after each
iteration. With the default settings, the time of the batched solver at B = 1024 is bimodal on
a small machine, because its temporary tensors are mapped and unmapped (and faulted in again)
on every Jacobian. The environment variables ``MALLOC_MMAP_THRESHOLD_=16777216
MALLOC_TRIM_THRESHOLD_=67108864``, jemalloc or tcmalloc have the same effect.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import scipy
import torch
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent))
import nist_strd  # noqa: E402

from torchfit.solver import LMOptions, keep_heap, levenberg_marquardt  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nist-strd"

# NumPy versions of the models for the scipy loop (a torch model there would add overhead).
NUMPY_MODELS = {
    "Misra1a": lambda b, x: b[0] * (1 - np.exp(-b[1] * x)),
    "Chwirut2": lambda b, x: np.exp(-b[0] * x) / (b[1] + b[2] * x),
    "Rat43": lambda b, x: b[0] / (1 + np.exp(b[1] - b[2] * x)) ** (1 / b[3]),
    "Gauss1": lambda b, x: (
        b[0] * np.exp(-b[1] * x)
        + b[2] * np.exp(-((x - b[3]) ** 2) / b[4] ** 2)
        + b[5] * np.exp(-((x - b[6]) ** 2) / b[7] ** 2)
    ),
}


def _starts(prob: nist_strd.NistProblem, batch: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    jitter = 1 + 0.2 * (torch.rand(batch, prob.n_params, generator=gen, dtype=torch.float64) - 0.5)
    return prob.start2[None] * jitter


def _run_case(args: argparse.Namespace) -> dict:
    if args.keep_heap and not keep_heap():
        raise SystemExit("--keep-heap: the C library is not glibc; nothing to set")
    if args.threads:
        torch.set_num_threads(args.threads)
    prob = nist_strd.load_problem(Path(args.data) / f"{args.problem}.dat")
    x0 = _starts(prob, args.batch, args.seed)
    tol = {"ftol": args.tol, "xtol": args.tol, "gtol": args.tol}
    times, solved = [], 0
    # One untimed warm-up run (first-call imports and allocations), then the timed repeats.
    for rep in range(args.repeats + 1):
        if args.method == "torchfit":
            opts = LMOptions(max_iter=args.max_iter, **tol)
            t0 = time.perf_counter()
            res = levenberg_marquardt(prob.residual, x0, opts, jacobian=args.jacobian)
            times.append(time.perf_counter() - t0)
            x = res.x
        else:
            model = NUMPY_MODELS[prob.name]
            xd, yd = prob.x.numpy(), prob.y.numpy()

            def fun(v: np.ndarray, model=model, xd=xd, yd=yd) -> np.ndarray:
                return yd - model(v, xd)

            out = []
            t0 = time.perf_counter()
            for b in range(args.batch):
                sol = least_squares(
                    fun,
                    x0[b].numpy(),
                    method="lm",
                    max_nfev=args.max_iter * (prob.n_params + 1),
                    **tol,
                )
                out.append(sol.x)
            times.append(time.perf_counter() - t0)
            x = torch.from_numpy(np.stack(out))
        lre = nist_strd.log_relative_error(x, prob.certified[None]).amin(dim=1)
        solved = int((lre >= 4).sum())
        if rep == 0:
            times.clear()
    return {
        "median_s": float(np.median(times)),
        "solved": solved,
        "maxrss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "threads": torch.get_num_threads(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problem", default="Chwirut2", choices=sorted(NUMPY_MODELS))
    parser.add_argument("--batch-sizes", default="1,64,1024")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scipy-repeats", type=int, default=1, help="repeats at B >= 1024")
    parser.add_argument("--jacobian", default="autograd")
    parser.add_argument("--max-iter", type=int, default=200)
    parser.add_argument("--tol", type=float, default=1e-10)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", default=str(DEFAULT_DATA))
    parser.add_argument(
        "--keep-heap",
        action="store_true",
        help="run every case with glibc malloc keeping its heap (see the module docstring)",
    )
    parser.add_argument("--case", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--method", default="torchfit", help=argparse.SUPPRESS)
    parser.add_argument("--batch", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.case:
        print(json.dumps(_run_case(args)))
        return

    print(f"machine: {platform.machine()} {platform.processor() or ''} | {os.cpu_count()} CPUs")
    print(
        f"python {platform.python_version()} | torch {torch.__version__} | numpy "
        f"{np.__version__} | scipy {scipy.__version__} | {platform.platform()}"
    )
    print(
        f"problem {args.problem} from Start 2 jittered +-10 %, float64, tol {args.tol:g}, "
        f"jacobian={args.jacobian}, torch threads={args.threads or 'default'}; "
        f"peak memory = ru_maxrss of a fresh process per case"
    )
    if args.keep_heap:
        print("malloc: torchfit.solver.keep_heap() in every case (mmap 16 MiB, trim 64 MiB)")
    header = (
        f"{'B':>6s} {'method':>9s} {'median s':>10s} {'problems/s':>11s} {'solved':>8s} "
        f"{'peak RSS MiB':>13s}"
    )
    print(header)
    for batch in [int(b) for b in args.batch_sizes.split(",")]:
        rates = {}
        for method in ("torchfit", "scipy"):
            repeats = args.repeats
            if method == "scipy" and batch >= 1024:
                repeats = args.scipy_repeats
            cmd = [
                sys.executable,
                __file__,
                "--case",
                "--method",
                method,
                "--batch",
                str(batch),
                "--problem",
                args.problem,
                "--repeats",
                str(repeats),
                "--jacobian",
                args.jacobian,
                "--max-iter",
                str(args.max_iter),
                "--tol",
                str(args.tol),
                "--threads",
                str(args.threads),
                "--seed",
                str(args.seed),
                "--data",
                args.data,
            ] + (["--keep-heap"] if args.keep_heap else [])
            out = subprocess.run(cmd, capture_output=True, text=True, check=True)
            res = json.loads(out.stdout.strip().splitlines()[-1])
            rates[method] = batch / res["median_s"]
            print(
                f"{batch:6d} {method:>9s} {res['median_s']:10.4f} {rates[method]:11.1f} "
                f"{res['solved']:>4d}/{batch:<4d}{res['maxrss_mib']:13.0f}",
                flush=True,
            )
        print(f"{batch:6d} {'speed-up':>9s} {rates['torchfit'] / rates['scipy']:10.1f}x")


if __name__ == "__main__":
    main()
