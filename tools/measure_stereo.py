"""Measure subjects from their posture-5 stereo pair (second paper): joints3d + lengths.

    python tools/measure_stereo.py --config configs/stereo.yaml [--data DIR] [--out DIR]

For every subject with a ``stereo/`` folder: segment both views, label the joints on each
silhouette (B-spline curvature + the paper's rules + wrists from skin colour), triangulate by
the midpoint method and write, under ``OUT/<subject>/``, ``joints3d.json``
(``{"joints_world": {name: [x, y, z]}}``), ``measurements.json`` and the overlays
``overlay_left.png`` / ``overlay_right.png`` (spline, extrema, cuts, joints; true joints as
white crosses where truth.json has them). ``OUT/summary.csv`` has one row per subject (status,
failed rule, message, lengths) and, where truth exists, ``OUT/errors.csv`` the per-subject
joint errors (mm) and length errors (%). Exit code 0 when every subject was measured, 1 when
some failed, 2 for a setup error.
"""

from __future__ import annotations

import argparse
import csv
import io
import logging
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from torchfit.config import config_to_yaml
from torchfit.config.cli import add_config_args, config_from_args, exit_code, run_folder
from torchfit.errors import OutputError, TorchfitError
from torchfit.io.dataset import load_dataset
from torchfit.io.export import write_json
from torchfit.io.files import write_atomic
from torchfit.io.images import write_image
from torchfit.parts import STEREO_MEASUREMENT_KEYS, project_joints
from torchfit.pipeline.stereo import measure_stereo_pair
from torchfit.viz.parts import draw_labelling

log = logging.getLogger("measure_stereo")


def errors_row(result, truth: dict) -> dict[str, float]:
    """Per-subject errors: joints in mm against joints_world.stereo, lengths in %."""
    row: dict[str, float] = {}
    true_joints = truth.get("joints_world", {}).get("stereo", {})
    errs = []
    for name, xyz in result.joints_world.items():
        if name in true_joints:
            e = 1000 * float(np.linalg.norm(np.subtract(xyz, true_joints[name])))
            row[f"{name}_mm"] = e
            errs.append(e)
    if errs:
        row["mean_joint_mm"] = float(np.mean(errs))
    for key, value in result.measurements.items():
        if key in truth:
            row[f"{key[:-2]}_pct"] = 100 * (value - truth[key]) / truth[key]
    return row


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_config_args(parser)
    args = parser.parse_args(argv)
    try:
        config = config_from_args(args)
        if config.data.root is None:
            raise TorchfitError("data.root: expected a dataset folder (--data DIR), got none")
        subjects = load_dataset(config.data.root, config.data.subjects)
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if all(s.stereo is None for s in subjects):  # nothing to measure: nothing is written
        why = [f"  {s.name}: {w}" for s in subjects for w in s.warnings if "stereo" in w]
        print(
            f"error: no subject in {config.data.root} has a usable stereo/ folder (cameras.yaml, "
            "left and right images, background/left/ and background/right/; design.md section "
            "7)" + "".join("\n" + line for line in why),
            file=sys.stderr,
        )
        return 2
    out = run_folder(config)
    try:
        return _measure(config, subjects, out)
    except OutputError as exc:  # the run folder cannot be written
        print(f"error: {exc}", file=sys.stderr)
        return exit_code(exc)


def _csv(rows: list[dict], fields: list[str]) -> str:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=fields, restval="")
    writer.writeheader()
    writer.writerows(rows)
    return text.getvalue()


def _measure(config, subjects, out: Path) -> int:
    write_atomic(out / "config.yaml", config_to_yaml(config))
    rows, error_rows = [], []
    for subject in tqdm(subjects, desc="stereo", unit="subject"):
        row = {"subject": subject.name}
        if subject.stereo is None:
            row.update(status="skipped", failed_rule="", message="no usable stereo/ folder")
            rows.append(row)
            continue
        folder = out / subject.name
        try:
            result = measure_stereo_pair(subject.stereo, config.parts, config.segmentation)
        except TorchfitError as exc:  # an unreadable image: this subject only
            row.update(status="failed", failed_rule="data", message=str(exc))
            rows.append(row)
            continue
        truth = subject.truth or {}
        true_joints = truth.get("joints_world", {}).get("stereo")
        for side, view in result.views.items():
            cam = getattr(subject.stereo, side)
            marks = project_joints(true_joints, cam) if true_joints else None
            picture = draw_labelling(view.image, view.labelling, view.mask, marks)
            write_image(folder / f"overlay_{side}.png", picture)
        row.update(
            status=result.status,
            failed_rule=result.failed_rule or "",
            message=result.message or "; ".join(result.notes),
        )
        if result.status == "ok":
            write_json(folder / "joints3d.json", {"joints_world": result.joints_world})
            write_json(folder / "measurements.json", result.measurements)
            row.update({k: f"{v:.5f}" for k, v in result.measurements.items()})
            if truth:
                error_rows.append({"subject": subject.name, **errors_row(result, truth)})
        else:
            tqdm.write(f"FAILED {subject.name}: {result.message}")
        rows.append(row)
    fields = ["subject", "status", "failed_rule", "message", *STEREO_MEASUREMENT_KEYS]
    write_atomic(out / "summary.csv", _csv(rows, fields))
    if error_rows:
        keys = sorted({k for r in error_rows for k in r} - {"subject"})
        formatted = [
            {k: (f"{v:.2f}" if isinstance(v, float) else v) for k, v in r.items()}
            for r in error_rows
        ]
        write_atomic(out / "errors.csv", _csv(formatted, ["subject", *keys]))
    failed = sum(r["status"] == "failed" for r in rows)
    skipped = sum(r["status"] == "skipped" for r in rows)
    measured = len(rows) - failed - skipped
    note = f", {skipped} skipped (no usable stereo/ folder)" if skipped else ""
    print(f"{measured} of {len(rows)} subjects measured, {failed} failed{note}; results in {out}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
