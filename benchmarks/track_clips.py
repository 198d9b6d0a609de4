"""Tracking accuracy on the CMU clips of benchmarks/RESULTS.md, in one command: each clip made,
its body fitted from its six postures, then tracked; one table.

    python benchmarks/track_clips.py --out DIR [--clips dev|wide|test] [--tag NAME]
        [--set KEY=VALUE ...] [--true-silhouettes] [--threads 1]
        [--mocap ../shared/data/cmu-mocap-sample]

The clips (`tools/make_sequence.py`, from the CMU motion capture in `--mocap`):

- `dev`: the ten development clips of "Test sequences that stand on the floor" (`01_01.bvh`,
  40 frames, every 4th, from each clip's start with its seed); tune on these;
- `wide`: those ten and twenty more from `01_01.bvh` (ten other stretches, and the ten
  stretches again on other bodies and rooms), for settings whose effect the ten clips' spread
  hides; tune on these too;
- `test`: the held-out clip (`11_01.amc`, 60 frames from 200, every 4th, seed 19); report it,
  never tune on it (a run of its own: the two sets are never averaged together).

Each clip is made once into `DIR/clips/<name>` (again where it has no
`sequence/synth.json`: a clip made before that file counted a BVH's frames from its rest pose)
and its subject fitted once with `configs/benchmark.yaml` into `DIR/fits/<name>` (kept: later
runs into the same `DIR` reuse them). It is then tracked with `configs/track.yaml` and the
`--set` overrides (`track.*`, `segmentation.*`) into `DIR/<tag>/<name>`; with
`--true-silhouettes`, from the clip's true silhouettes instead of its segmentation (a folder
`DIR/clips/<name>/true_silhouettes/` linking the sequence, `truth_masks/` as its `masks/`). Writes
`DIR/<tag>/track_clips.md` and `.csv`: per clip the mean joint error (design.md's joints but
head_top), its parts along and across the camera's rays, the statuses and the tracker's ms per
frame; then the mean and the median over the clips. Needs the `synth` extra (anny) to make the
clips.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[1]


class Clip(NamedTuple):
    """A test sequence as ``tools/make_sequence.py`` makes it."""

    name: str
    motion: str  # file name in the mocap folder
    start: int
    seed: int
    frames: int = 40
    step: int = 4


#: The development clips (01_01.bvh) and the held-out one (11_01.amc).
CLIPS = {
    "dev": [
        Clip("dev01", "01_01.bvh", 300, 11),
        Clip("dev_s1000", "01_01.bvh", 1000, 23),
        Clip("dev_s1400", "01_01.bvh", 1400, 67),
        Clip("dev_s1800", "01_01.bvh", 1800, 37),
        Clip("dev_s2300", "01_01.bvh", 2300, 41),
        Clip("dev_s600", "01_01.bvh", 600, 53),
        Clip("dev_s0", "01_01.bvh", 0, 59),
        Clip("dev_s1200", "01_01.bvh", 1200, 71),
        Clip("dev_s2000", "01_01.bvh", 2000, 67),
        Clip("dev_s2500", "01_01.bvh", 2500, 73),
    ],
    "test": [Clip("test11", "11_01.amc", 200, 19, frames=60)],
}
#: ``wide``: the ten development clips and twenty more from the same motion (other stretches,
#: and the same stretches on other bodies and rooms), for settings whose effect the ten clips'
#: spread hides.
CLIPS["wide"] = CLIPS["dev"] + [
    Clip(f"wide_s{start}", "01_01.bvh", start, seed)
    for start, seed in [
        (100, 101), (450, 103), (800, 107), (1100, 109), (1300, 113),
        (1600, 127), (1900, 131), (2150, 137), (2400, 139), (2590, 149),
        (0, 151), (300, 157), (600, 163), (1000, 167), (1200, 173),
        (1400, 179), (1800, 181), (2000, 191), (2300, 193), (2500, 197),
    ]
]  # fmt: skip

#: The table's columns (eval.json keys of ``tools/track.py``).
COLUMNS = ("mean_joint_error_mm", "along_ray_mm", "across_ray_mm", "ms_per_frame")
STATUSES = ("ok", "recovered", "uncertain")


def _run(cmd: list[str]) -> None:
    print("$", " ".join(cmd), flush=True)
    done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    # tools/track.py exits 1 when a sequence has uncertain frames: its outputs are written
    if done.returncode not in (0, 1):
        sys.exit(f"{Path(cmd[1]).name} failed (exit {done.returncode}):\n{done.stderr[-2000:]}")


def make_and_fit(clip: Clip, mocap: Path, out: Path, threads: int) -> tuple[Path, Path]:
    """The clip's sequence folder and its fitted subject folder, made where missing."""
    data, fit = out / "clips" / clip.name, out / "fits" / clip.name
    # a clip made before sequences said what made them (sequence/synth.json) counted a BVH's
    # frames from its rest pose, one capture frame earlier: made again (its subject is the same)
    if not (data / "sequence" / "synth.json").is_file():
        _run(
            [sys.executable, str(ROOT / "tools" / "make_sequence.py"), "--bvh",
             str(mocap / clip.motion), "--out", str(data), "--frames", str(clip.frames),
             "--start", str(clip.start), "--step", str(clip.step), "--seed", str(clip.seed)]
        )  # fmt: skip
    if not (fit / "subject" / "params.json").is_file():
        _run(
            [sys.executable, str(ROOT / "tools" / "fit.py"), "--config",
             str(ROOT / "configs" / "benchmark.yaml"), "--data", str(data), "--out", str(fit),
             "--set", "data.subjects=[subject]", "--set", "output.overlays=false",
             "--set", "output.tensorboard=false", "--set", f"run.num_threads={threads}"]
        )  # fmt: skip
    return data / "sequence", fit / "subject"


def with_true_silhouettes(sequence: Path) -> Path:
    """A sequence folder beside ``sequence`` whose ``masks/`` are its true silhouettes
    (``truth_masks/``), the rest linked: tracked with ``segmentation.method: masks`` it shows
    what the tracker does with a perfect segmentation."""
    folder = sequence.parent / "true_silhouettes"
    folder.mkdir(exist_ok=True)
    links = {"camera.yaml": "camera.yaml", "frames": "frames", "truth.json": "truth.json"}
    links["masks"] = "truth_masks"
    for name, target in links.items():
        if not (folder / name).is_symlink():
            (folder / name).symlink_to((sequence / target).resolve())
    return folder


def track(sequence: Path, model: Path, out: Path, sets: list[str], threads: int) -> dict:
    """Track one clip with ``configs/track.yaml`` and ``sets``; its ``eval.json``."""
    cmd = [
        sys.executable, str(ROOT / "tools" / "track.py"), "--config",
        str(ROOT / "configs" / "track.yaml"), "--model", str(model), "--sequence", str(sequence),
        "--out", str(out), "--threads", str(threads),
    ]  # fmt: skip
    for s in sets:
        cmd += ["--set", s]
    _run(cmd)
    return json.loads((out / "eval.json").read_text())


def summarise(results: dict[str, dict]) -> tuple[str, list[list[str]]]:
    """A markdown table and CSV rows of clip name -> ``eval.json``; with several clips, the
    mean (the statuses and the frames on a second silhouette summed) and the median."""
    header = ["clip", "joint error mm", "along the rays", "across", "ms per frame", *STATUSES]
    header.append("bridged")  # frames tracked to their second silhouette (light legs)
    counts = {
        n: [ev.get("status", {}).get(s, 0) for s in STATUSES] + [ev.get("bridged_frames", 0)]
        for n, ev in results.items()
    }
    rows = [
        [name, *(f"{ev[c]:.1f}" for c in COLUMNS), *map(str, counts[name])]
        for name, ev in results.items()
    ]
    if len(results) > 1:
        values = {c: [ev[c] for ev in results.values()] for c in COLUMNS}
        totals = [str(sum(col)) for col in zip(*counts.values(), strict=True)]
        rows.append(["mean", *(f"{statistics.fmean(values[c]):.1f}" for c in COLUMNS), *totals])
        rows.append(
            ["median", *(f"{statistics.median(values[c]):.1f}" for c in COLUMNS)]
            + [""] * (len(STATUSES) + 1)
        )
    lines = [
        "| " + " | ".join(header) + " |",
        "|---|" + "--:|" * (len(header) - 1),
        *("| " + " | ".join(r) + " |" for r in rows),
    ]
    return "\n".join(lines) + "\n", [header, *rows]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--clips", choices=tuple(CLIPS), default="dev")
    parser.add_argument("--tag", default="shipped", help="name of this tracking run's folder")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument(
        "--true-silhouettes",
        action="store_true",
        help="track each clip from its true silhouettes (truth_masks/ as masks/)",
    )
    parser.add_argument(
        "--mocap", type=Path, default=ROOT.parent / "shared" / "data" / "cmu-mocap-sample"
    )
    args = parser.parse_args()
    clips = CLIPS[args.clips]
    missing = sorted({c.motion for c in clips if not (args.mocap / c.motion).is_file()})
    if missing:
        parser.error(f"--mocap {args.mocap}: missing {missing}")
    results = {}
    for clip in clips:
        sequence, model = make_and_fit(clip, args.mocap, args.out, args.threads)
        sets = args.set
        if args.true_silhouettes:
            sequence = with_true_silhouettes(sequence)
            sets = [*sets, "segmentation.method=masks"]
        results[clip.name] = track(
            sequence, model, args.out / args.tag / clip.name, sets, args.threads
        )
    table, rows = summarise(results)
    sets = " ".join(f"--set {s}" for s in args.set) or "(shipped config)"
    sets += " --true-silhouettes" if args.true_silhouettes else ""
    text = f"# Tracking `{args.tag}` on the {args.clips} clips: {sets}\n\n{table}"
    (args.out / args.tag / "track_clips.md").write_text(text)
    with (args.out / args.tag / "track_clips.csv").open("w", newline="") as f:
        csv.writer(f).writerows(rows)
    print(text)


if __name__ == "__main__":
    main()
