"""Compare the measurements of captured subject folders with those of a reference folder, all
fitted in one run (benchmarks/RESULTS.md, Calibration and capture).

    python benchmarks/compare_captures.py RUN_DIR [RUN_DIR ...] --reference original \
        --captured h1 h7 [--reference original_clean ...]

For each captured subject and each reference, prints the per-measurement difference in
percent of the reference's value and the largest absolute one. With ``--subjects DIR`` (the
subject folders that were fitted) also the silhouettes: per posture, the pixels where the
captured image's segmentation (default options, against the reference's background frames)
differs from the reference's. Reads
``RUN_DIR/<subject>/measurements.json`` (written by tools/fit.py) from the first run folder
that has it (a subject's fit does not depend on the others fitted in its batch). Exit codes:
0 printed, 4 a measurements file missing or unreadable.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchfit.errors import TorchfitError  # noqa: E402
from torchfit.measurements import MEASUREMENT_KEYS  # noqa: E402

#: the first paper's seven measurements (design.md section 5)
KEYS = MEASUREMENT_KEYS[:7]


def _measurements(runs: list[Path], subject: str) -> dict[str, float]:
    paths = [run / subject / "measurements.json" for run in runs]
    path = next((p for p in paths if p.is_file()), paths[0])
    data = json.loads(path.read_text())
    flat = data.get("measurements", data)
    return {k: float(flat[k]) for k in KEYS if k in flat}


def _background_model(folder: Path):
    """The segmentation's background model (default options) of a subject folder."""
    from torchfit.image.background import fit_background
    from torchfit.image.segment import SegmentationOptions
    from torchfit.io.images import load_frames

    return fit_background(load_frames(folder / "background")[0], SegmentationOptions())


def _masks(folder: Path, model):
    """(6, H, W) silhouettes of a subject folder's postures against a background model."""
    from torchfit.image.segment import SegmentationOptions, segment
    from torchfit.io.images import load_frames

    poses = [folder / "poses" / f"pose{k}.png" for k in range(1, 7)]
    return segment(load_frames(poses)[0], model, SegmentationOptions()).masks[:, 0].numpy()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, nargs="+", help="the fits' run folders")
    parser.add_argument("--reference", action="append", required=True, help="subject name")
    parser.add_argument("--captured", nargs="+", required=True, help="subject names")
    parser.add_argument("--subjects", type=Path, help="compare the silhouettes too")
    args = parser.parse_args(argv)
    try:
        refs = {r: _measurements(args.run, r) for r in args.reference}
        caps = {c: _measurements(args.run, c) for c in args.captured}
    except (OSError, ValueError, KeyError) as exc:
        print(f"error: cannot read the measurements ({exc})", file=sys.stderr)
        return 4
    for ref, base in refs.items():
        print(f"against {ref}:")
        print("  " + " ".join(f"{k[:-2]:>15}" for k in base) + "  max |%|")
        for cap, values in caps.items():
            diffs = [100.0 * (values[k] - v) / v for k, v in base.items()]
            row = " ".join(f"{d:+15.2f}" for d in diffs)
            print(f"  {row}  {max(abs(d) for d in diffs):6.2f}  {cap}")
    if args.subjects is None:
        return 0
    try:
        for ref in args.reference:
            model = _background_model(args.subjects / ref)  # once per reference
            base = _masks(args.subjects / ref, model)
            print(f"silhouette pixels differing from {ref}'s, pose1..pose6 and total:")
            for cap in args.captured:
                masks = _masks(args.subjects / cap, model)
                counts = [int((a ^ b).sum()) for a, b in zip(masks, base, strict=True)]
                print(f"  {' '.join(f'{c:6d}' for c in counts)}  {sum(counts):7d}  {cap}")
    except (OSError, ValueError, TorchfitError) as exc:
        print(f"error: cannot compare the silhouettes ({exc})", file=sys.stderr)
        return 4
    return 0


if __name__ == "__main__":
    sys.exit(main())
