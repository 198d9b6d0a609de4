"""Speed of the six-posture fit: autograd LM against the paper's numeric MINPACK baseline, and
batch throughput, optionally against another checkout of the project.

    python benchmarks/bench_fit.py --data DIR [--config configs/benchmark.yaml]
        [--baseline-subjects 1] [--batch-sizes 1,4,16] [--threads N] [--set KEY=VALUE ...]
        [--against CHECKOUT] [--repeats 1] [--shared K] [--shared-subjects 2]

Part 1 (same subject, same residual, same stopping rule, one run): one stage over every
scale and the root poses of the six postures, from the template start, solved (a) by the
batched LM with the structured autograd Jacobian and (b) by MINPACK lmdif with forward
differences on the rendered-contour residual (torchfit.fit.baseline). Both final costs are
evaluated with the rendered residual, so they compare one to one.

Part 2: wall time of the whole configured fit (segmentation included) for B subjects in one
batch, for each B; subjects are taken from DIR in order (repeated if DIR has fewer).
``--batch-sizes ""`` skips it.

``--against CHECKOUT`` (e.g. ``git worktree add /tmp/base <commit>``): Part 2 instead times
each (checkout, B) in a fresh ``python -c`` process run in that checkout with
``PYTHONPATH=CHECKOUT``, so that each side imports its own ``torchfit`` and reads its own
config file at the same relative path as ``--config``; the time is that of
``torchfit.pipeline.run`` alone. The runs alternate this, other, this, other ... ``--repeats``
times per B; the table gives medians and the median of the per-pair throughput ratios.
``--threads N`` reaches the processes (``OMP_NUM_THREADS``, ``MKL_NUM_THREADS``,
``torch.set_num_threads`` and ``run.num_threads``).

``--shared K``: K processes of this checkout at once, each fitting its own ``--shared-subjects``
subjects at B = 1 with one thread, against one process fitting all of them with K threads;
whole-process wall times (one import per process included), alternating, ``--repeats`` times.

Prints markdown tables, the machine and the versions.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchfit.body.model import BodyModel  # noqa: E402
from torchfit.camera import stack_cameras  # noqa: E402
from torchfit.config import load_config, replace_keys  # noqa: E402
from torchfit.fit import SilhouetteFit, StageOptions, solve_stage  # noqa: E402
from torchfit.fit.baseline import minpack_stage, rendered_residual  # noqa: E402
from torchfit.io.dataset import load_dataset  # noqa: E402
from torchfit.pipeline import person_data, run, segment_subject  # noqa: E402
from torchfit.solver import LMOptions  # noqa: E402

#: The result line a fresh-process run prints.
MARK = "BENCH_FIT_RESULT "

#: One fresh-process run: argv[1] is the JSON of ``checkout``, ``config``, ``sets``, ``keys``,
#: ``threads`` and ``mark``; only APIs that older checkouts have too.
SNIPPET = """
import json, sys, time
from pathlib import Path
a = json.loads(sys.argv[1])
import torch
if a["threads"]:
    torch.set_num_threads(a["threads"])
import torchfit
from torchfit.config import load_config, replace_keys
from torchfit.pipeline import run
where = Path(torchfit.__file__).resolve()
if Path(a["checkout"]).resolve() not in where.parents:
    sys.exit(f"imported {where}, not the torchfit of {a['checkout']}")
config = load_config(a["config"], a["sets"])
keys = dict(a["keys"])
if a["threads"] and hasattr(config.run, "num_threads"):
    keys["run.num_threads"] = a["threads"]
config = replace_keys(config, keys)
t = time.perf_counter()
results = run(config, Path(keys["run.out"]))
wall = time.perf_counter() - t
statuses = sorted({str(r.status) for r in results})
print(a["mark"] + json.dumps(
    {"wall": wall, "statuses": statuses, "threads": torch.get_num_threads()}
), flush=True)
"""


def machine() -> str:
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__} ({torch.get_num_threads()} threads), "
        f"python {platform.python_version()}"
    )


def fit_problem(config, subjects) -> SilhouetteFit:
    """The fitting problem of ``subjects``, segmented as ``config`` says (float64)."""
    model = BodyModel(config.model.template)
    segmented = [segment_subject(s, config) for s in subjects]
    person = person_data(
        config,
        torch.stack([m for _, m, _ in segmented]),
        torch.stack([sh for _, _, sh in segmented]),
        stack_cameras([s.camera for s in subjects]),
        torch.float64,
    )
    bounds = (config.model.scale_min, config.model.scale_max)
    return SilhouetteFit(model, person, config.fit, bounds)


def part1(config, subjects, max_iter: int, lm_factor: int = 4) -> None:
    fit = fit_problem(config, subjects)
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


def link_subjects(root: Path, names: list[str], folder: Path, first: int = 0) -> Path:
    """``folder`` holding links ``NNN_name`` to ``root/name`` for ``names``, numbered from
    ``first``."""
    folder.mkdir(parents=True)
    root = root.resolve()  # a relative link would point from the temporary folder
    for i, name in enumerate(names, first):
        os.symlink(root / name, folder / f"{i:03d}_{name}")
    return folder


def fit_keys(data: Path, out: Path, b: int) -> dict:
    """The config keys Part 2 replaces for a run over ``data`` into ``out`` in batches of b."""
    return {
        "data.root": str(data),
        "data.subjects": None,
        "run.out": str(out),
        "run.resume": False,
        "fit.batch_size": b,
        "output.tensorboard": False,
    }


def cycle(names: list[str], n: int) -> list[str]:
    """``n`` names: ``names`` in order, repeated as needed."""
    return [names[i % len(names)] for i in range(n)]


def part2(config, root: Path, names: list[str], batch_sizes: list[int]) -> None:
    print("\n## Whole fit, batch throughput (segmentation + all stages + outputs)\n")
    print("| B | wall s | s per subject | subjects per minute | statuses |")
    print("|---|---|---|---|---|")
    for b in batch_sizes:
        with tempfile.TemporaryDirectory() as tmp:
            data = link_subjects(root, cycle(names, b), Path(tmp) / "data")
            cfg = replace_keys(config, fit_keys(data, Path(tmp) / "run", b))
            t = time.perf_counter()
            results = run(cfg, Path(cfg.run.out))
            wall = time.perf_counter() - t
            statuses = sorted({r.status for r in results})
            print(f"| {b} | {wall:.0f} | {wall / b:.1f} | {60 * b / wall:.2f} | {statuses} |")
            shutil.rmtree(Path(tmp) / "run", ignore_errors=True)


def spawn(
    checkout: Path, config: Path, sets: list[str], keys: dict, threads: int | None, log: Path
) -> subprocess.Popen:
    """Start :data:`SNIPPET` in a fresh process that imports ``checkout``'s torchfit."""
    env = dict(os.environ, PYTHONPATH=str(checkout))
    if threads:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    payload = {
        "checkout": str(checkout),
        "config": str(config),
        "sets": sets,
        "keys": keys,
        "threads": threads,
        "mark": MARK,
    }
    with open(log, "w") as out:
        return subprocess.Popen(
            [sys.executable, "-c", SNIPPET, json.dumps(payload)],
            cwd=checkout,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )


def collect(proc: subprocess.Popen, log: Path) -> dict:
    """Wait for a :func:`spawn` ed process; its result (``wall``, ``statuses``, ``threads``).

    Raises:
        RuntimeError: the process failed or printed no result.
    """
    proc.wait()
    lines = log.read_text().splitlines()
    found = [line[len(MARK) :] for line in lines if line.startswith(MARK)]
    if proc.returncode or not found:
        tail = "\n".join(lines[-30:])
        raise RuntimeError(f"a fit process failed (exit {proc.returncode}); its output:\n{tail}")
    return json.loads(found[-1])


def collect_all(jobs: list[tuple[subprocess.Popen, Path]]) -> list[dict]:
    """:func:`collect` each job; the others are killed when one fails."""
    try:
        return [collect(proc, log) for proc, log in jobs]
    finally:
        for proc, _ in jobs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def fresh_run(
    checkout: Path,
    config: Path,
    sets: list[str],
    root: Path,
    names: list[str],
    b: int,
    threads: int | None,
) -> dict:
    """One Part 2 run of B subjects in a fresh process of ``checkout``."""
    with tempfile.TemporaryDirectory() as tmp:
        data = link_subjects(root, cycle(names, b), Path(tmp) / "data")
        keys = fit_keys(data, Path(tmp) / "run", b)
        log = Path(tmp) / "log.txt"
        start = cpu_seconds()
        res = collect(spawn(checkout, config, sets, keys, threads, log), log)
        res["others"] = others(start)
        return res


def cpu_seconds() -> tuple[float, float, float]:
    """Busy CPU seconds of the whole machine so far (nan without ``/proc/stat``), those of this
    process and its waited-for children, and the wall clock."""
    try:
        ticks = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
        busy = sum(int(ticks[i]) for i in (0, 1, 2, 5, 6)) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        busy = float("nan")
    own = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        usage = resource.getrusage(who)
        own += usage.ru_utime + usage.ru_stime
    return busy, own, time.perf_counter()


def others(start: tuple[float, float, float]) -> float:
    """Mean cores busy with other processes since ``start`` (:func:`cpu_seconds`): the
    machine's busy time less this process's and its children's (nan when unknown)."""
    busy, own, now = cpu_seconds()
    if busy != busy:
        return busy
    return max(0.0, (busy - start[0]) - (own - start[1])) / (now - start[2])


def others_note(values: list[float]) -> str:
    """The other processes' load over the timed runs, with a warning when it skews them."""
    known = [v for v in values if v == v]
    if not known:
        return "Other processes' load during the runs: unknown (no /proc/stat)."
    worst = max(known)
    note = f"Other processes kept up to {worst:.2f} cores busy during a run"
    if worst > 0.25:
        note += (
            f" of {os.cpu_count()}: the times are skewed (threads waiting on a shared core can "
            "slow a fit many times over); repeat on an idle machine"
        )
    return note + "."


def describe(checkout: Path) -> str:
    """The checkout's commit (``-dirty`` with uncommitted changes), or ``?``."""
    try:
        out = subprocess.run(
            ["git", "-C", str(checkout), "describe", "--always", "--dirty"],
            capture_output=True,
            text=True,
            check=True,
        )
    except (OSError, subprocess.CalledProcessError):
        return "?"
    return out.stdout.strip()


def checkout_config(checkout: Path, config: Path) -> Path:
    """``checkout``'s config file at the path ``config`` has in this checkout (``config``
    itself when it lies outside this checkout)."""
    try:
        return checkout / config.resolve().relative_to(ROOT)
    except ValueError:
        return config.resolve()


def thread_note(used: dict[str, set[int]], how: str) -> str:
    """The torch thread counts the fresh processes' ``run()`` ran with."""
    seen = ", ".join(f"{side} {sorted(n)}" for side, n in used.items())
    return f"Torch threads in run() ({how}): {seen}."


def part2_against(
    config_path: Path,
    sets: list[str],
    root: Path,
    names: list[str],
    batch_sizes: list[int],
    other: Path,
    repeats: int,
    threads: int | None,
) -> None:
    sides = {"this": ROOT, "against": other}
    configs = {side: checkout_config(path, config_path) for side, path in sides.items()}
    walls: dict[tuple[str, int], list[float]] = {}
    statuses: dict[tuple[str, int], set[str]] = {}
    used: dict[str, set[int]] = {side: set() for side in sides}
    busy: list[float] = []
    for b in batch_sizes:
        for r in range(repeats):
            for side, checkout in sides.items():
                res = fresh_run(checkout, configs[side], sets, root, names, b, threads)
                walls.setdefault((side, b), []).append(res["wall"])
                statuses.setdefault((side, b), set()).update(res["statuses"])
                used[side].add(res["threads"])
                busy.append(res["others"])
                print(
                    f"  B={b} run {r + 1}/{repeats} {side}: {res['wall']:.1f} s "
                    f"(others {res['others']:.2f} cores)",
                    file=sys.stderr,
                    flush=True,
                )
    print(
        "\n## Whole fit, batch throughput, this checkout against another "
        "(segmentation + all stages + outputs)\n"
    )
    for side, path in sides.items():
        print(f"- {side}: {path} ({describe(path)}), config {configs[side]}")
    print(
        "\n| B | this s per subject | this subjects per minute | against s per subject | "
        "against subjects per minute | this / against | statuses this / against |"
    )
    print("|---|---|---|---|---|---|---|")
    rate: dict[tuple[str, int], float] = {}
    for b in batch_sizes:
        for side in sides:
            rate[side, b] = 60 * b / statistics.median(walls[side, b])
        ratio = statistics.median(
            a / t for t, a in zip(walls["this", b], walls["against", b], strict=True)
        )
        cells = " | ".join(
            f"{statistics.median(walls[side, b]) / b:.1f} | {rate[side, b]:.2f}" for side in sides
        )
        print(
            f"| {b} | {cells} | {ratio:.2f}x | "
            f"{sorted(statuses['this', b])} / {sorted(statuses['against', b])} |"
        )
    print(
        f"\nTimes are `torchfit.pipeline.run()` alone, each run in a fresh process (process start "
        f"and imports excluded), medians of {repeats} run(s) per cell, run alternately this, "
        "against; this / against is the median of the per-pair ratios of subjects per minute."
    )
    big = max(batch_sizes)
    if 1 in batch_sizes and big > 1:
        scaling = ", ".join(f"{side} {rate[side, big] / rate[side, 1]:.2f}x" for side in sides)
        print(f"B = {big} / B = 1 throughput: {scaling}.")
    how = (
        f"--threads {threads}"
        if threads
        else "no --threads: as each checkout's run() chose, OMP_NUM_THREADS "
        + os.environ.get("OMP_NUM_THREADS", "unset")
    )
    print(thread_note(used, how))
    print(others_note(busy))
    for b in batch_sizes:
        raw = "; ".join(
            f"{side} " + ", ".join(f"{w:.1f}" for w in walls[side, b]) for side in sides
        )
        print(f"run() s at B = {b}: {raw}.")


def shared(
    config,
    config_path: Path,
    sets: list[str],
    root: Path,
    names: list[str],
    k: int,
    m: int,
    repeats: int,
) -> None:
    picked = cycle(names, k * m)
    config_file = config_path.resolve()
    has_threads = any(f.name == "num_threads" for f in dataclasses.fields(config.run))
    walls: dict[str, list[float]] = {"shared": [], "single": []}
    statuses: dict[str, set[str]] = {"shared": set(), "single": set()}
    used: dict[str, set[int]] = {"shared": set(), "single": set()}
    busy: list[float] = []
    for r in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            # K processes at once, each its own M subjects at B = 1 with one thread
            extra = ["run.num_threads=1"] if has_threads else []
            folders = [
                link_subjects(root, picked[i * m : (i + 1) * m], tmp / f"data{i}", i * m)
                for i in range(k)
            ]
            start = cpu_seconds()
            jobs = []
            for i, folder in enumerate(folders):
                keys = fit_keys(folder, tmp / f"run{i}", 1)
                log = tmp / f"log{i}.txt"
                jobs.append((spawn(ROOT, config_file, sets + extra, keys, 1, log), log))
            results = collect_all(jobs)
            walls["shared"].append(time.perf_counter() - start[2])
            busy.append(others(start))
            for res in results:
                statuses["shared"].update(res["statuses"])
                used["shared"].add(res["threads"])
            # one process, all K*M subjects at B = 1 with K threads
            extra = [f"run.num_threads={k}"] if has_threads else []
            keys = fit_keys(link_subjects(root, picked, tmp / "data"), tmp / "run", 1)
            log = tmp / "log.txt"
            start = cpu_seconds()
            res = collect(spawn(ROOT, config_file, sets + extra, keys, k, log), log)
            walls["single"].append(time.perf_counter() - start[2])
            busy.append(others(start))
            statuses["single"].update(res["statuses"])
            used["single"].add(res["threads"])
        print(
            f"  shared run {r + 1}/{repeats}: shared {walls['shared'][-1]:.1f} s, "
            f"single {walls['single'][-1]:.1f} s (others {busy[-2]:.2f}, {busy[-1]:.2f} cores)",
            file=sys.stderr,
            flush=True,
        )
    n = k * m
    print(f"\n## Processes sharing the machine ({ROOT}, {describe(ROOT)}, config {config_file})\n")
    print("| way | processes x threads | subjects | wall s | subjects per minute | statuses |")
    print("|---|---|---|---|---|---|")
    shape = {"shared": f"{k} x 1", "single": f"1 x {k}"}
    for way in walls:
        wall = statistics.median(walls[way])
        print(
            f"| {way} | {shape[way]} | {n} | {wall:.1f} | {60 * n / wall:.2f} | "
            f"{sorted(statuses[way])} |"
        )
    ratio = statistics.median(
        s1 / s0 for s0, s1 in zip(walls["shared"], walls["single"], strict=True)
    )
    print(
        f"\nshared / single subjects per minute: {ratio:.2f}x (median of the per-pair ratios). "
        f"Shared: {k} processes started at once, {m} subject(s) each at B = 1, "
        f"{'run.num_threads=1' if has_threads else 'one thread'}; single: one process, all "
        f"{n} subjects at B = 1 with {k} threads. Wall times are whole processes, from just "
        "before the first starts to when the last ends, so each way includes one Python, torch "
        f"and torchfit import per process; medians of {repeats} run(s), alternating shared, "
        "single. --threads does not apply here."
    )
    print(thread_note(used, f"shared 1 each, single {k}"))
    print(others_note(busy))
    raw = "; ".join(f"{way} " + ", ".join(f"{w:.1f}" for w in walls[way]) for way in walls)
    print(f"whole-process s: {raw}.")


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
    parser.add_argument(
        "--against", type=Path, metavar="CHECKOUT", help="time Part 2 against this checkout"
    )
    parser.add_argument(
        "--repeats", type=int, default=1, help="runs per case (--against, --shared)"
    )
    parser.add_argument("--shared", type=int, metavar="K", help="K processes sharing the machine")
    parser.add_argument("--shared-subjects", type=int, default=2, metavar="M")
    args = parser.parse_args()
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    if args.repeats > 1 and not (args.against or args.shared):
        parser.error("--repeats applies to --against and --shared only")
    if args.shared is not None and (args.shared < 1 or args.shared_subjects < 1):
        parser.error("--shared and --shared-subjects must be >= 1")
    other = args.against.resolve() if args.against else None
    if other is not None:
        if not (other / "torchfit").is_dir():
            parser.error(f"--against {args.against}: no torchfit package there")
        if not checkout_config(other, args.config).is_file():
            parser.error(f"--against: no {checkout_config(other, args.config)}")
    if args.threads:
        torch.set_num_threads(args.threads)
    config = load_config(args.config, args.set)
    subjects = [s for s in load_dataset(args.data) if s.ok]
    names = [s.name for s in subjects]
    print(f"# bench_fit on {args.data} ({machine()})" + "".join(f" --set {o}" for o in args.set))
    if not args.skip_baseline:
        part1(config, subjects[: args.baseline_subjects], args.baseline_max_iter)
    sizes = [int(b) for b in args.batch_sizes.split(",") if b]
    if sizes and other is not None:
        part2_against(
            args.config,
            args.set,
            args.data.resolve(),
            names,
            sizes,
            other,
            args.repeats,
            args.threads,
        )
    elif sizes:
        part2(config, args.data, names, sizes)
    if args.shared:
        shared(
            config,
            args.config,
            args.set,
            args.data.resolve(),
            names,
            args.shared,
            args.shared_subjects,
            args.repeats,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
