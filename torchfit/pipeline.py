"""Wire the stages for a dataset; the only place a config enters the library.

Per subject: validate the folder, segment the six posture images against the background
frames, build the template body, pose it at the six nominal postures facing the subject's
camera, and write measurements, parameters, the exchangeable model and overlays of the model
contour (green) over the person's contour (magenta) on every posture image. The per-subject
parameters are what the fit (the first paper's Levenberg–Marquardt) refines; until it runs,
``status`` says ``template`` and the measurements are the template's.

One bad subject never stops the others: it gets ``status = failed`` and the reason.
"""

from __future__ import annotations

import csv
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchfit.body.measure import measure_model
from torchfit.body.model import BodyModel
from torchfit.body.postures import POSTURES, pose_nominal
from torchfit.camera import camera_centre, project_points
from torchfit.config import Config, save_config
from torchfit.errors import DataError, TorchfitError
from torchfit.io.dataset import Subject, load_dataset
from torchfit.io.export import export_mesh, export_urdf, write_json
from torchfit.io.images import load_frames
from torchfit.measurements import MEASUREMENT_KEYS
from torchfit.render import draw_polyline, render_silhouette
from torchfit.segmentation import fit_background, segment

__all__ = ["SubjectResult", "run", "process_subject"]

log = logging.getLogger(__name__)

_DONE_FILES = ("measurements.json", "params.json")


@dataclass
class SubjectResult:
    """Outcome of one subject (a row of summary.csv)."""

    name: str
    status: str  # "template", "ok", "failed"
    message: str = ""
    measurements: dict[str, float] = field(default_factory=dict)
    final_cost: float | None = None
    iterations: int | None = None
    seconds: float = 0.0

    def row(self) -> dict:
        row = {"subject": self.name, "status": self.status}
        row.update({k: self.measurements.get(k) for k in MEASUREMENT_KEYS})
        row.update(
            final_cost=self.final_cost,
            iterations=self.iterations,
            seconds=round(self.seconds, 3),
            message=self.message,
        )
        return row


def _outline(mask: np.ndarray) -> list[np.ndarray]:
    import cv2

    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return [c[:, 0, :].astype(np.float64) for c in contours]


def _overlay(image: np.ndarray, person: np.ndarray | None, model_mask: np.ndarray, label: str):
    import cv2

    out = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    if person is not None:
        for c in _outline(person):
            draw_polyline(out, c, (255, 0, 255), thickness=2)
    for c in _outline(model_mask):
        draw_polyline(out, c, (0, 200, 0), thickness=2)
    cv2.putText(out, label, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (0, 0, 0), 3)
    cv2.putText(out, label, (10, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 1)
    return out


def process_subject(
    subject: Subject, model: BodyModel, config: Config, folder: Path
) -> SubjectResult:
    """Process one subject and write its outputs under ``folder``.

    Raises:
        TorchfitError: for bad input (the caller turns it into a failed status).
    """
    import cv2

    start = time.perf_counter()
    if subject.problems:
        raise DataError("; ".join(subject.problems))
    cam = subject.camera
    background, _ = load_frames(subject.background, size=cam.image_size)
    images, _ = load_frames(subject.poses, size=cam.image_size)
    seg = segment(images, fit_background(background, config.segmentation), config.segmentation)
    missing = [f"pose{i + 1}" for i, ok in enumerate(seg.found.tolist()) if not ok]
    if missing:
        log.warning("%s: no person found in %s", subject.name, ", ".join(missing))

    dtype = model.dtype
    scales = torch.ones(1, model.num_segments, 3, dtype=dtype, device=model.device)
    centre = camera_centre(cam.R, cam.t).to(dtype)
    camera = cam.to(dtype=dtype)
    folder.mkdir(parents=True, exist_ok=True)
    poses = {}
    for posture in POSTURES:
        params, out = pose_nominal(model, scales, posture, centre)
        poses[f"pose{posture.index}"] = {
            "name": posture.name,
            "joint_angles": dict(
                zip(model.dof_names, params["joint_angles"][0].tolist(), strict=True)
            ),
            "root_translation": params["root_translation"][0],
            "root_rotation": params["root_rotation"][0],
        }
        if config.output.overlays:
            px = project_points(out.vertices, camera)[0].cpu().numpy()
            model_mask = render_silhouette(px, model.faces.cpu().numpy(), cam.image_size)
            image = (images[posture.index - 1].permute(1, 2, 0).numpy() * 255).round()
            person = seg.masks[posture.index - 1, 0].numpy()
            overlay = _overlay(
                image.astype(np.uint8),
                person,
                model_mask,
                f"{subject.name} pose{posture.index} {posture.name}",
            )
            cv2.imwrite(str(folder / f"overlay_pose{posture.index}.png"), overlay)

    measurements = {k: float(v[0]) for k, v in measure_model(model, scales).items()}
    export_urdf(model, scales[0], folder)
    export_mesh(
        model(**{**model.zeros(1), "scales": scales}).vertices[0],
        model.faces,
        folder / f"model.{config.output.mesh_format}",
    )
    status = "template"
    message = "template measurements at the nominal postures (no fit)"
    write_json(
        folder / "params.json",
        {
            "template": model.template.name,
            "status": status,
            "message": message,
            "scales": dict(zip(model.template.segments, scales[0].tolist(), strict=True)),
            "poses": poses,
        },
    )
    write_json(folder / "measurements.json", {**measurements, "status": status})
    return SubjectResult(
        subject.name, status, message, measurements, seconds=time.perf_counter() - start
    )


def _resumed(subject: Subject, folder: Path) -> SubjectResult | None:
    if not all((folder / f).is_file() for f in _DONE_FILES):
        return None
    try:
        data = json.loads((folder / "measurements.json").read_text())
    except json.JSONDecodeError:
        return None
    values = {k: float(data[k]) for k in MEASUREMENT_KEYS if k in data}
    return SubjectResult(subject.name, data.get("status", "ok"), "resumed: outputs on disk", values)


def write_summary(results: list[SubjectResult], path: Path) -> None:
    """Write summary.csv, one row per subject."""
    rows = [r.row() for r in results]
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(SubjectResult("", "").row()))
        writer.writeheader()
        writer.writerows(rows)


def run(
    config: Config,
    run_dir: Path,
    progress: Callable[[list[Subject]], object] | None = None,
) -> list[SubjectResult]:
    """Run a whole dataset: the resolved config, per-subject outputs and summary.csv.

    Args:
        config: the resolved configuration (``data.root`` must be set).
        run_dir: the run folder.
        progress: optional wrapper over the subject list (e.g. ``tqdm``).

    Returns:
        One :class:`SubjectResult` per subject, failed ones included.
    """
    if not config.data.root:
        raise DataError("data.root is not set: pass --data DIR or set data.root in the config")
    run_dir.mkdir(parents=True, exist_ok=True)
    save_config(config, run_dir / "config.yaml")
    subjects = load_dataset(config.data.root, config.data.subjects)
    if not subjects:
        raise DataError(f"no subject folders found in {config.data.root}")
    dtype = torch.float64 if config.run.dtype == "float64" else torch.float32
    model = BodyModel(config.model.template, device=config.run.device, dtype=dtype)
    results = []
    iterator = progress(subjects) if progress else subjects
    for subject in iterator:
        folder = run_dir / subject.name
        if config.run.resume and (done := _resumed(subject, folder)):
            results.append(done)
            continue
        try:
            results.append(process_subject(subject, model, config, folder))
        except (TorchfitError, OSError) as exc:
            log.error("%s: %s", subject.name, exc)
            results.append(SubjectResult(subject.name, "failed", str(exc)))
        write_summary(results, run_dir / "summary.csv")
    write_summary(results, run_dir / "summary.csv")
    return results
