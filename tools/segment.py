"""Segment the person in every image of a folder against a background model.

    python tools/segment.py --background DIR --images DIR --out DIR \
        [--config FILE] [--set segmentation.threshold=5] [--truth DIR]

``--config`` is a torchfit config YAML (the same file the other tools read); only its
``segmentation:`` section is used here, e.g.::

    segmentation:
      threshold: 4.0
      gamma: 0.3
      background: frames          # or temporal_median (frames may show the person)

With ``background: frames`` the ``--background`` folder holds >= ``min_background_frames``
frames of the empty scene; with ``temporal_median`` it holds frames that may show the person
(it may be the ``--images`` folder itself).

Writes ``OUT/<stem>.png`` (0 background, 255 person) for every image where a person was found
and ``OUT/status.csv`` (file, status, message). With ``--truth DIR`` it prints precision, recall
and F-measure against CDnet-style label images (``gtNNNNNN.png`` for ``inNNNNNN.*``, otherwise
the same stem); an image where no person was found counts there as an empty mask, an unreadable
or wrongly sized image is not scored. It also prints the fraction of the true cast-shadow
pixels kept as background: those labelled 50 (CDnet) and, for a synthetic subject's
``--truth SUBJECT/truth_masks``, those of ``<stem>_shadow.png`` beside each label image.
Exit code: 0 if every image was segmented, 1 if any failed, 2 for a setup error.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402
from tqdm import tqdm  # noqa: E402

from torchfit.config import Config, load_config  # noqa: E402
from torchfit.errors import SegmentationError, TorchfitError  # noqa: E402
from torchfit.eval.metrics import cdnet_counts, precision_recall_f  # noqa: E402
from torchfit.image import fit_background, segment  # noqa: E402
from torchfit.io import list_images, load_frames, read_image, read_mask, write_mask  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--background", required=True, type=Path, help="folder of background frames")
    p.add_argument("--images", required=True, type=Path, help="folder of images to segment")
    p.add_argument("--out", required=True, type=Path, help="folder for the mask PNGs")
    p.add_argument("--config", type=Path, help="torchfit config YAML (segmentation: section)")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key, e.g. segmentation.threshold=5 (repeatable)",
    )
    p.add_argument("--truth", type=Path, help="folder of ground-truth label images to score")
    p.add_argument("--batch-size", type=int, default=8, help="images per batch (default 8)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    args = p.parse_args(argv)
    if args.batch_size < 1:
        p.error(f"--batch-size must be >= 1, got {args.batch_size}")
    return args


def truth_path(truth_dir: Path, image: Path) -> Path | None:
    """``gtNNNNNN.png`` for ``inNNNNNN.*`` (CDnet naming), else a file with the same stem."""
    stem = image.stem
    stems = ["gt" + stem[2:], stem] if stem.startswith("in") else [stem]
    for s in stems:
        for suffix in (".png", ".bmp", ".jpg"):
            if (truth_dir / f"{s}{suffix}").is_file():
                return truth_dir / f"{s}{suffix}"
    return None


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        device = torch.device(args.device)
    except RuntimeError as exc:
        print(f"error: --device: {exc}", file=sys.stderr)
        return 2
    if device.type == "cuda" and not torch.cuda.is_available():
        print(
            f"error: --device: {args.device!r} but torch sees no CUDA device here", file=sys.stderr
        )
        return 2
    try:
        cfg = load_config(args.config, args.set, schema=Config).segmentation
        frames, _ = load_frames(args.background)
        model = fit_background(frames.to(args.device), cfg)
        paths = list_images(args.images)
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not paths:
        print(f"error: no images found in {args.images}", file=sys.stderr)
        return 2
    width, height = model.size
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"error: cannot create {args.out}: {exc.strerror}", file=sys.stderr)
        return 2
    status: dict[Path, tuple[str, str]] = {}
    totals: dict[str, int] = {}
    scored, missing_truth = 0, 0

    bar = tqdm(total=len(paths), unit="img", desc="segment")
    for start in range(0, len(paths), args.batch_size):
        batch, batch_paths = [], []
        for path in paths[start : start + args.batch_size]:
            try:
                img = read_image(path)
                if img.shape[:2] != (height, width):
                    raise SegmentationError(
                        f"{path}: expected size {width}x{height} (WxH) of the background, "
                        f"got {img.shape[1]}x{img.shape[0]}"
                    )
            except TorchfitError as exc:
                status[path] = ("failed", str(exc))
                bar.write(f"FAILED {path.name}: {exc}")
                bar.update(1)
                continue
            batch.append(torch.from_numpy(img).permute(2, 0, 1))
            batch_paths.append(path)
        if not batch:
            continue
        images = torch.stack(batch).to(args.device, torch.float32) / 255.0
        result = segment(images, model, cfg)
        for i, path in enumerate(batch_paths):
            mask = result.masks[i, 0]
            if bool(result.found[i]):
                write_mask(args.out / f"{path.stem}.png", mask)
                status[path] = ("ok", "")
            else:
                status[path] = ("failed", f"{path}: no person found (empty mask after clean-up)")
                bar.write(f"FAILED {path.name}: no person found")
            if args.truth is not None:
                gt = truth_path(args.truth, path)
                if gt is None:
                    missing_truth += 1
                else:
                    shadow = gt.with_name(f"{gt.stem}_shadow.png")
                    try:
                        counts = cdnet_counts(mask, read_mask(gt))
                        cast = None  # make_subjects.py's truth_masks/poseK_shadow.png
                        if shadow.is_file():
                            cast = read_mask(shadow, (width, height)) > 127
                    except TorchfitError as exc:
                        bar.write(f"truth {gt.name} not scored: {exc}")
                        missing_truth += 1
                    else:
                        scored += 1
                        if cast is not None:
                            counts["shadow"] += int(cast.sum())
                            counts["shadow_as_background"] += int(
                                (cast & ~mask.cpu().numpy().astype(bool)).sum()
                            )
                        for k, v in counts.items():
                            totals[k] = totals.get(k, 0) + v
            bar.update(1)
    bar.close()

    with open(args.out / "status.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["file", "status", "message"])
        for path in paths:
            writer.writerow([path.name, *status[path]])
    failed = sum(1 for s, _ in status.values() if s != "ok")
    print(
        f"{len(paths) - failed} of {len(paths)} images segmented, {failed} failed; "
        f"masks in {args.out}"
    )
    if args.truth is not None:
        if scored:
            precision, recall, f = precision_recall_f(totals)
            print(
                f"scored {scored} images ({missing_truth} without ground truth): "
                f"precision {precision:.4f}  recall {recall:.4f}  F-measure {f:.4f}"
            )
            if totals.get("shadow"):
                frac = totals["shadow_as_background"] / totals["shadow"]
                print(f"cast-shadow pixels kept as background: {frac:.4f} of {totals['shadow']}")
        else:
            print(
                f"no ground truth scored in {args.truth} for these images ({missing_truth} "
                "without one that could be read)"
            )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
