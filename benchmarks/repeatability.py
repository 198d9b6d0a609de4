"""Repeatability: how far the measurements move under changes too small to matter.

The dataset is fitted once as it is, then once per perturbation. Each fit runs
`tools/fit.py` in a fresh process. Per measurement the report gives the mean and largest
|change|, in % of the first fit's value, and it lists the subjects whose status changed. The
perturbations (`--perturb`, comma-separated):

- `noise`: every posture and background image with Gaussian noise of `--noise` grey levels
  added (seeded, rounded back to 8 bits; at 1 grey level the images look the same);
- `float32`: the same images, fitted with `run.dtype=float32`;
- `batch`: the same images, each subject fitted alone (`fit.batch_size=1`). The fit is
  batch-invariant, so this must report zero.

A fit that is repeatable moves by much less than its error against the truth. The capture
target of "within 1 % of the original images" needs less than 1 %.

    python benchmarks/repeatability.py --data DIR --out DIR [--config configs/benchmark.yaml]
        [--perturb noise,float32,batch] [--noise 1.0] [--seed 0] [--threads 1] [--set k=v ...]

Writes `repeatability.md` and `repeatability.csv` into `--out`, and the runs beside them.
"""

from __future__ import annotations

import argparse
import csv
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from torchfit.measurements import MEASUREMENT_KEYS

ROOT = Path(__file__).resolve().parents[1]
#: the first paper's measurements (the second paper's three follow them in MEASUREMENT_KEYS)
KEYS = MEASUREMENT_KEYS[:7]
PERTURBATIONS = ("noise", "float32", "batch")


def noisy_copy(data: Path, out: Path, sigma: float, seed: int) -> Path:
    """A copy of the subject folders of ``data`` under ``out`` with noise added to every
    posture and background image (``stereo/`` and ``truth_masks/`` are left out)."""
    rng = np.random.default_rng(seed)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for subject in sorted(p for p in data.iterdir() if (p / "camera.yaml").is_file()):
        dest = out / subject.name
        shutil.copytree(subject, dest, ignore=shutil.ignore_patterns("stereo", "truth_masks"))
        for image in sorted([*dest.glob("poses/*.png"), *dest.glob("background/*.png")]):
            pixels = cv2.imread(str(image), cv2.IMREAD_UNCHANGED).astype(np.float64)
            pixels += rng.normal(0.0, sigma, pixels.shape)
            cv2.imwrite(str(image), np.clip(np.round(pixels), 0, 255).astype(np.uint8))
    return out


def fit(config: str, data: Path, out: Path, threads: int, sets: list[str]) -> dict[str, dict]:
    """Run tools/fit.py; its summary rows by subject."""
    cmd = [
        sys.executable,
        str(ROOT / "tools" / "fit.py"),
        "--config",
        config,
        "--data",
        str(data),
        "--out",
        str(out),
        "--set",
        "output.overlays=false",
        "--set",
        "output.tensorboard=false",
        "--set",
        f"run.num_threads={threads}",
    ]
    for s in sets:
        cmd += ["--set", s]
    print("$", " ".join(cmd), flush=True)
    done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    summary = out / "summary.csv"
    if done.returncode not in (0, 1) or not summary.is_file():
        sys.exit(f"tools/fit.py failed (exit {done.returncode}):\n{done.stderr[-2000:]}")
    with summary.open(newline="") as f:
        return {row["subject"]: row for row in csv.DictReader(f)}


def changes(base: dict[str, dict], other: dict[str, dict]) -> tuple[np.ndarray, list[str]]:
    """(N, K) |change| in % per subject fitted in both runs and measurement, and the subjects
    whose status changed (``name: a -> b``)."""
    rows, moved = [], []
    for name in sorted(set(base) & set(other)):
        a, b = base[name], other[name]
        if a["status"] != b["status"]:
            moved.append(f"{name}: {a['status']} -> {b['status']}")
        try:
            rows.append([100 * abs(float(b[k]) / float(a[k]) - 1) for k in KEYS])
        except (ValueError, ZeroDivisionError):
            continue  # a failed fit has no measurements
    return np.array(rows).reshape(-1, len(KEYS)), moved


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--config", default="configs/benchmark.yaml")
    parser.add_argument("--perturb", default=",".join(PERTURBATIONS))
    parser.add_argument("--noise", type=float, default=1.0, help="grey levels (standard deviation)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    chosen = [p for p in args.perturb.split(",") if p]
    unknown = sorted(set(chosen) - set(PERTURBATIONS))
    if unknown:
        parser.error(f"--perturb: unknown {unknown}; choose from {list(PERTURBATIONS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    base = fit(args.config, args.data, args.out / "base", args.threads, args.set)
    table = []
    for name in chosen:
        if name == "noise":
            data = noisy_copy(args.data, args.out / "noisy_data", args.noise, args.seed)
            other = fit(args.config, data, args.out / "noise", args.threads, args.set)
            label = f"noise, {args.noise:g} grey levels (seed {args.seed})"
        elif name == "float32":
            sets = [*args.set, "run.dtype=float32"]
            other = fit(args.config, args.data, args.out / "float32", args.threads, sets)
            label = "float32"
        else:
            sets = [*args.set, "fit.batch_size=1"]
            other = fit(args.config, args.data, args.out / "batch", args.threads, sets)
            label = "one subject per batch"
        delta, moved = changes(base, other)
        table.append((label, delta, moved))
    header = "| perturbation | n | " + " | ".join(k[:-2].replace("_", " ") for k in KEYS)
    lines = [
        f"# Repeatability of `{args.config}` on `{args.data}`",
        "",
        "Mean |change| % (largest) of each measurement against the unperturbed fit.",
        "",
        header + " | status changed |",
        "|---|--:|" + "--:|" * len(KEYS) + "---|",
    ]
    with (args.out / "repeatability.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["perturbation", "statistic", *KEYS])
        for label, delta, moved in table:
            mean = delta.mean(0) if len(delta) else np.full(len(KEYS), np.nan)
            top = delta.max(0) if len(delta) else np.full(len(KEYS), np.nan)
            cells = " | ".join(f"{m:.2f} ({t:.2f})" for m, t in zip(mean, top, strict=True))
            lines.append(f"| {label} | {len(delta)} | {cells} | {'; '.join(moved) or 'none'} |")
            writer.writerow([label, "mean_abs_change_pct", *(f"{v:.4f}" for v in mean)])
            writer.writerow([label, "max_abs_change_pct", *(f"{v:.4f}" for v in top)])
    text = "\n".join(lines) + "\n"
    (args.out / "repeatability.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
