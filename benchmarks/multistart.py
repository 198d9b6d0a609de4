"""Several starts per subject: does the lowest final cost, or the median over starts, measure
better than one fit?

    python benchmarks/multistart.py --data DIR [--config configs/benchmark.yaml] [--starts 4]
        [--sigma 0.01] [--out FILE.json]

Each subject of DIR with ``truth.json`` is fitted ``--starts`` times in one batch: from the
template start, and from it plus Gaussian noise of ``--sigma`` on every parameter (log scales,
radians, metres; seeded, clipped to the bounds). Prints the mean absolute error % of one fit
(the plain start), of the median of the starts' measurements, of the start with the lowest
final cost, and the mean spread (max - min) over the starts, per measurement.
"""

from __future__ import annotations

import argparse
import importlib
import json
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchfit.body.measure import measure_model  # noqa: E402
from torchfit.body.model import BodyModel  # noqa: E402
from torchfit.camera import stack_cameras  # noqa: E402
from torchfit.config import load_config  # noqa: E402
from torchfit.io.dataset import load_dataset  # noqa: E402
from torchfit.pipeline.prepare import person_data, prepare_subject  # noqa: E402
from torchfit.pipeline.runtime import apply_runtime  # noqa: E402
from torchfit.pipeline.stages import run_stages  # noqa: E402

KEYS = ["height_m", "arm_span_m", "lower_leg_m", "thigh_m", "upper_arm_m", "forearm_m"]
KEYS += ["shoulder_width_m"]


def fit_starts(data: Path, config, starts: int, sigma: float) -> list[dict]:
    run_module = importlib.import_module("torchfit.pipeline.run")
    subjects = [s for s in load_dataset(data) if s.ok and s.truth]
    rows = [p for p in (prepare_subject(s, config) for s in subjects) for _ in range(starts)]
    model = BodyModel(config.model.template)
    used = [j - 1 for j in config.fit.poses]
    person = person_data(
        config,
        torch.stack([p.masks[used] for p in rows]),
        torch.stack([p.shadow[used] for p in rows]),
        stack_cameras([p.subject.camera for p in rows]),
        model.dtype,
    )
    fit = run_module.build_problem(model, person, config, [p.subject.facts for p in rows])
    x0 = fit.initial_params()
    noise = sigma * torch.randn(
        x0.shape, generator=torch.Generator().manual_seed(0), dtype=x0.dtype
    )
    noise[::starts] = 0  # each subject's first start is the plain one
    x0 = torch.minimum(torch.maximum(x0 + noise, fit.lower), fit.upper)
    x, _ = run_stages(fit, x0, config, [p.subject.name for p in rows])
    measures = measure_model(model, model.expand_scales(fit.layout.group_scales(x)))
    final = fit.residual(x, fit.select(x))
    cost = 0.5 * (final**2).sum(1)
    return [
        {
            "name": p.subject.name,
            "start": i % starts,
            "cost": float(cost[i]),
            "measurements": {k: float(measures[k][i]) for k in KEYS},
            "truth": {k: p.subject.truth[k] for k in KEYS},
        }
        for i, p in enumerate(rows)
    ]


def report(results: list[dict]) -> None:
    by: dict[str, list[dict]] = {}
    for r in results:
        by.setdefault(r["name"], []).append(r)

    def pct(m: dict, t: dict) -> list[float]:
        return [100 * abs(m[k] - t[k]) / t[k] for k in KEYS]

    ways: dict[str, list[list[float]]] = {"one fit": [], "median": [], "lowest cost": []}
    ways["spread"] = []
    for rs in by.values():
        t = rs[0]["truth"]
        ways["one fit"].append(pct(rs[0]["measurements"], t))
        med = {k: statistics.median(r["measurements"][k] for r in rs) for k in KEYS}
        ways["median"].append(pct(med, t))
        ways["lowest cost"].append(pct(min(rs, key=lambda r: r["cost"])["measurements"], t))
        ways["spread"].append(
            [
                100
                * (max(r["measurements"][k] for r in rs) - min(r["measurements"][k] for r in rs))
                / t[k]
                for k in KEYS
            ]
        )
    print("| way | " + " | ".join(k[:-2].replace("_", " ") for k in KEYS) + " |")
    print("|---|" + "--:|" * len(KEYS))
    for way, rows in ways.items():
        cells = " | ".join(f"{statistics.mean(c):.2f}" for c in zip(*rows, strict=True))
        print(f"| {way} | {cells} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--config", type=Path, default=Path("configs/benchmark.yaml"))
    parser.add_argument("--starts", type=int, default=4)
    parser.add_argument("--sigma", type=float, default=0.01)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    config = load_config(args.config, args.set)
    apply_runtime(config.run)
    results = fit_starts(args.data, config, args.starts, args.sigma)
    if args.out:
        args.out.write_text(json.dumps(results, indent=1))
    report(results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
