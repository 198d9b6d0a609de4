"""Chroma key against the true silhouettes of green-screen subjects.

    python tools/make_subjects.py --config configs/synth_greenscreen.yaml --out DIR --n 4 \
        --seed 5000
    python benchmarks/eval_chroma_key.py --data DIR [--config configs/chroma_key.yaml]

For every posture image: precision, recall and F-measure of the silhouette against
``truth_masks/pose<k>.png``, with ``segmentation.method: chroma_key`` (the config's
``chroma_key`` section) and, for comparison, background subtraction with the same frames.
Prints one line per subject and method and the means.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchfit.config import load_config  # noqa: E402
from torchfit.errors import TorchfitError  # noqa: E402
from torchfit.io import read_mask  # noqa: E402
from torchfit.io.dataset import load_dataset  # noqa: E402
from torchfit.pipeline.prepare import segment_subject  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def scores(mask: torch.Tensor, truth: torch.Tensor) -> tuple[float, float, float]:
    """Precision, recall and F-measure of a (H, W) bool mask against the truth."""
    tp = float((mask & truth).sum())
    p = tp / max(float(mask.sum()), 1.0)
    r = tp / max(float(truth.sum()), 1.0)
    return p, r, 2 * p * r / max(p + r, 1e-12)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, type=Path)
    parser.add_argument("--config", type=Path, default=REPO / "configs" / "chroma_key.yaml")
    args = parser.parse_args(argv)
    config = load_config(args.config)
    totals: dict[str, list[tuple[float, float, float]]] = {}
    for method in ("chroma_key", "background"):
        seg = dataclasses.replace(config.segmentation, method=method)
        for subject in load_dataset(args.data, method=method):
            try:
                _, masks, _ = segment_subject(subject, seg)
            except TorchfitError as exc:
                print(f"{subject.name} {method}: failed: {exc}")
                continue
            rows = []
            for k in range(6):
                truth = read_mask(subject.folder / "truth_masks" / f"pose{k + 1}.png") > 127
                rows.append(scores(masks[k], torch.from_numpy(truth)))
            totals.setdefault(method, []).extend(rows)
            f = [r[2] for r in rows]
            print(f"{subject.name} {method:10s} F per posture {' '.join(f'{v:.4f}' for v in f)}")
    for method, rows in totals.items():
        p, r, f = (statistics.mean(x[i] for x in rows) for i in range(3))
        print(f"mean {method:10s} precision {p:.4f} recall {r:.4f} F {f:.4f} ({len(rows)} images)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
