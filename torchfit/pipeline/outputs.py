"""What a fit run writes: per subject measurements.json, params.json, the fitted model and
overlays; per run summary.csv (README "What a run writes")."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchfit.body.model import BodyModel
from torchfit.body.postures import POSTURES
from torchfit.fit.model_contour import ContourSelection
from torchfit.fit.problem import SilhouetteFit
from torchfit.io.dataset import Subject
from torchfit.io.export import export_mesh, export_urdf
from torchfit.measurements import MEASUREMENT_KEYS
from torchfit.pipeline.prepare import PreparedSubject
from torchfit.pipeline.stages import StageRecord
from torchfit.status import SubjectStatus
from torchfit.viz.overlay import fit_overlay

__all__ = [
    "DONE_FILES",
    "SubjectResult",
    "pose_record",
    "params_document",
    "write_overlays",
    "write_model",
    "write_summary",
    "resumed_result",
]

#: A subject whose folder holds these is finished (a rerun resumes it).
DONE_FILES = ("measurements.json", "params.json")


@dataclass
class SubjectResult:
    """Outcome of one subject (a row of summary.csv)."""

    name: str
    status: SubjectStatus
    message: str = ""
    measurements: dict[str, float] = field(default_factory=dict)
    final_cost: float | None = None
    iterations: int | None = None
    seconds: float = 0.0

    def row(self) -> dict:
        """The summary.csv row."""
        row = {"subject": self.name, "status": str(self.status)}
        row.update({k: self.measurements.get(k) for k in MEASUREMENT_KEYS})
        row.update(
            final_cost=self.final_cost,
            iterations=self.iterations,
            seconds=round(self.seconds, 3),
            message=self.message,
        )
        return row


def pose_record(fit: SilhouetteFit, x: torch.Tensor, i: int, j: int) -> dict:
    """params.json's record of posture j of subject ``i`` at parameters ``x`` (B, P)."""
    rows = torch.arange(x.shape[0], device=x.device)
    _, angles, rot, trans = fit.pose_state(x[i : i + 1], j, rows[i : i + 1])
    model = fit.model
    return {
        "name": POSTURES[j - 1].name,
        "joint_angles": dict(zip(model.dof_names, angles[0].tolist(), strict=True)),
        "free_joints": fit.layout.free_joint_names(j),
        "root_translation_xy": trans[0, :2],
        "root_rotation": rot[0],
        "offsets": fit.layout.root_offsets(x[i], j),
    }


def params_document(
    fit: SilhouetteFit,
    x: torch.Tensor,
    i: int,
    scales: torch.Tensor,
    status: SubjectStatus,
    message: str,
    method: str,
    start: dict,
    stages: list[StageRecord],
) -> dict:
    """The params.json document of subject ``i``.

    Args:
        fit: the batch's problem.
        x: (B, P) fitted parameters.
        i: the subject's row.
        scales: (S, 3) its segment scales.
        status, message: the judged outcome.
        method: ``fit.method``.
        start: how its start was made (``{"source": "template"}`` or a StartInfo dict).
        stages: its stage records.
    """
    model = fit.model
    group = fit.layout.group_scales(x)[i]
    return {
        "template": model.template.name,
        "status": str(status),
        "message": message,
        "method": method,
        "group_scales": {g: group[gi] for gi, g in enumerate(model.template.scale_groups)},
        "segment_scales": dict(zip(model.template.segments, scales.tolist(), strict=True)),
        "initial_guess": start,
        "poses": {f"pose{j}": pose_record(fit, x, i, j) for j in fit.poses},
        "stages": [s.to_dict() for s in stages],
    }


def write_overlays(
    folder: Path,
    prepared: PreparedSubject,
    fit: SilhouetteFit,
    selections: dict[int, ContourSelection],
    i: int,
    tb=None,
) -> None:
    """overlay_pose<j>.png of subject ``i`` for every fitted posture (and to TensorBoard).

    Args:
        folder: the subject's output folder.
        prepared: the subject's images, silhouettes and shadow pixels.
        fit: the batch's problem.
        selections: the final model-contour choice per posture.
        i: the subject's row in the batch.
        tb: optional :class:`torchfit.pipeline.tensorboard.TensorBoardCallback`.
    """
    import cv2

    name = prepared.subject.name
    for j in fit.poses:
        image = prepared.images[j - 1].permute(1, 2, 0).numpy()
        overlay = fit_overlay(
            (image * 255).round().astype(np.uint8),
            prepared.masks[j - 1].numpy(),
            selections[j].masks[i],
            f"{name} pose{j} {POSTURES[j - 1].name}",
            prepared.shadow[j - 1].numpy() if fit.person.uncertain is not None else None,
        )
        cv2.imwrite(str(folder / f"overlay_pose{j}.png"), overlay[:, :, ::-1])
        if tb is not None:
            tb.add_image(f"overlay/{name}/pose{j}", overlay)


def write_model(model: BodyModel, scales: torch.Tensor, folder: Path, mesh_format: str) -> None:
    """The fitted body: model.urdf + meshes/, and the neutral-pose mesh ``model.<format>``.

    Args:
        model: the body model.
        scales: (S, 3) the subject's segment scales.
        folder: the subject's output folder.
        mesh_format: ``glb`` or ``obj``.
    """
    export_urdf(model, scales, folder)
    neutral = model(scales[None], **{k: v for k, v in model.zeros(1).items() if k != "scales"})
    export_mesh(neutral.vertices[0], model.faces, folder / f"model.{mesh_format}")


def write_summary(results: list[SubjectResult], path: Path) -> None:
    """Write summary.csv, one row per subject."""
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(SubjectResult("", SubjectStatus.OK).row()))
        writer.writeheader()
        writer.writerows(r.row() for r in results)


def resumed_result(subject: Subject, folder: Path) -> SubjectResult | None:
    """The result of a subject finished by an earlier run (None when it is not finished)."""
    if not all((folder / f).is_file() for f in DONE_FILES):
        return None
    try:
        data = json.loads((folder / "measurements.json").read_text())
        status = SubjectStatus(data.get("status", "ok"))
    except (json.JSONDecodeError, ValueError):
        return None
    values = {k: float(data[k]) for k in MEASUREMENT_KEYS if k in data}
    return SubjectResult(subject.name, status, "resumed: outputs on disk", values)
