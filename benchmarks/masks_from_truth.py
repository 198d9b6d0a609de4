"""A copy of a synthetic dataset whose silhouettes come from ``masks/``: each subject's true
silhouettes (``truth_masks/pose<k>.png``, written by the generator) become its own masks, and
``background/`` is left out (the fit must not need it).

    python benchmarks/masks_from_truth.py --data /path/to/synthetic --out /tmp/with_masks
    python tools/benchmark.py --config configs/benchmark.yaml --data /tmp/with_masks \
        --out runs/masks

Fitting the copy measures what the fit reaches with perfect segmentation, beside fitting the
original folder (background subtraction) with the same config. ``camera.yaml``, ``poses/`` and
``truth.json`` are copied unchanged.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from tqdm import tqdm

N_POSES = 6


def copy_subject(src: Path, dst: Path) -> None:
    """Copy one subject folder with ``masks/`` from its true silhouettes and no background."""
    truth_masks = src / "truth_masks"
    missing = [k for k in range(1, N_POSES + 1) if not (truth_masks / f"pose{k}.png").is_file()]
    if missing:
        raise FileNotFoundError(f"{truth_masks}: no true silhouette for posture(s) {missing}")
    dst.mkdir(parents=True, exist_ok=True)
    for name in ("camera.yaml", "truth.json"):
        if (src / name).is_file():
            shutil.copy2(src / name, dst / name)
    shutil.copytree(src / "poses", dst / "poses", dirs_exist_ok=True)
    (dst / "masks").mkdir(exist_ok=True)
    for k in range(1, N_POSES + 1):
        shutil.copy2(truth_masks / f"pose{k}.png", dst / "masks" / f"pose{k}.png")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="synthetic dataset (subject folders)")
    parser.add_argument("--out", required=True, help="the copy to write")
    args = parser.parse_args(argv)
    root = Path(args.data)
    if not root.is_dir():
        print(f"error: dataset folder not found: {root}", file=sys.stderr)
        return 4
    subjects = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    try:
        for src in tqdm(subjects, desc="subjects", unit="subject"):
            copy_subject(src, Path(args.out) / src.name)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 4
    except OSError as exc:
        print(f"error: cannot write {args.out}: {exc}", file=sys.stderr)
        return 3
    print(f"{len(subjects)} subjects with masks/ written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
