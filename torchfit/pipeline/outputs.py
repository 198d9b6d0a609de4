"""What a fit run writes: per subject measurements.json, params.json, the fitted model and
overlays; per run summary.csv (README "What a run writes").

Every file is written atomically (:mod:`torchfit.io.files`). A subject's folder is finished
when its ``fingerprint.json`` (:mod:`torchfit.pipeline.fingerprint`), written last, is there;
before a subject is written again, :func:`clear_outputs` removes that file first, then the rest.
summary.csv rows of finished subjects are read back from their files
(:func:`result_from_disk`), so a resumed row is the row its fit wrote.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchfit.body.bvh import model_motion
from torchfit.body.model import BodyModel
from torchfit.body.postures import POSTURES
from torchfit.fit.model_contour import ContourSelection
from torchfit.fit.problem import SilhouetteFit
from torchfit.io.bvh import write_bvh
from torchfit.io.export import export_mesh, export_urdf
from torchfit.io.files import remove_files, remove_temporary, write_atomic
from torchfit.io.images import write_image
from torchfit.measurements import MEASUREMENT_KEYS
from torchfit.pipeline.prepare import PreparedSubject
from torchfit.pipeline.stages import StageRecord
from torchfit.status import SubjectStatus
from torchfit.viz.overlay import fit_overlay

__all__ = [
    "OUTPUT_FILES",
    "SubjectResult",
    "pose_record",
    "params_document",
    "write_overlays",
    "write_model",
    "write_summary",
    "result_from_disk",
    "clear_outputs",
]

#: The files of a subject folder that a run writes (besides ``overlay_pose<j>.png`` and
#: ``meshes/<segment>.obj``), the done marker first.
OUTPUT_FILES = (
    "fingerprint.json",
    "measurements.json",
    "params.json",
    "model.urdf",
    "model.bvh",
    "template.json",
    "model.glb",
    "model.obj",
)


@dataclass
class SubjectResult:
    """Outcome of one subject (a row of summary.csv; ``resumed``: kept from an earlier run)."""

    name: str
    status: SubjectStatus
    message: str = ""
    measurements: dict[str, float] = field(default_factory=dict)
    final_cost: float | None = None
    iterations: int | None = None
    seconds: float = 0.0
    resumed: bool = False

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
    seconds: float = 0.0,
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
        seconds: wall time spent on it (reading, segmenting, its share of the batch's fit).
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
        "seconds": round(seconds, 3),
    }


def write_overlays(
    folder: Path,
    prepared: PreparedSubject,
    fit: SilhouetteFit,
    selections: dict[int, ContourSelection],
    i: int,
    tb=None,
    bends: dict | None = None,
) -> None:
    """overlay_pose<j>.png of subject ``i`` for every fitted posture (and to TensorBoard).

    Args:
        folder: the subject's output folder.
        prepared: the subject's images, silhouettes and shadow pixels.
        fit: the batch's problem.
        selections: the final model-contour choice per posture.
        i: the subject's row in the batch.
        tb: optional :class:`torchfit.pipeline.tensorboard.TensorBoardCallback`.
        bends: optional params.json record of the bent-joint marks
            (:meth:`torchfit.fit.bends.BendFit.mark_record`), drawn on their postures.
    """
    name = prepared.subject.name
    bends = bends or {}
    for j in fit.poses:
        image = prepared.float_images([j - 1])[0].permute(1, 2, 0).numpy()
        overlay = fit_overlay(
            (image * 255).round().astype(np.uint8),
            prepared.masks[j - 1].numpy(),
            selections[j].mask(i),
            f"{name} pose{j} {POSTURES[j - 1].name}",
            prepared.shadow[j - 1].numpy() if fit.person.uncertain is not None else None,
            [(m["target_px"], m["model_px"]) for m in bends.get(f"pose{j}", {}).values()],
        )
        write_image(folder / f"overlay_pose{j}.png", overlay)
        if tb is not None:
            tb.add_image(f"overlay/{name}/pose{j}", overlay)


def write_model(model: BodyModel, scales: torch.Tensor, folder: Path, mesh_format: str) -> None:
    """The fitted body: model.urdf + meshes/, its skeleton in the neutral pose as
    ``model.bvh`` (its own segment lengths, for binding in an animation tool), and the
    neutral-pose mesh ``model.<format>``.

    Args:
        model: the body model.
        scales: (S, 3) the subject's segment scales.
        folder: the subject's output folder.
        mesh_format: ``glb`` or ``obj``.
    """
    export_urdf(model, scales, folder)
    write_bvh(folder / "model.bvh", model_motion(model, scales))
    neutral = model(scales[None], **{k: v for k, v in model.zeros(1).items() if k != "scales"})
    export_mesh(neutral.vertices[0], model.faces, folder / f"model.{mesh_format}")


def write_summary(results: list[SubjectResult], path: Path) -> None:
    """Write summary.csv, one row per subject (atomically)."""
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(SubjectResult("", SubjectStatus.OK).row()))
    writer.writeheader()
    writer.writerows(r.row() for r in results)
    write_atomic(path, text.getvalue())


def result_from_disk(name: str, folder: Path) -> SubjectResult | None:
    """A finished subject's summary row, read back from its measurements.json and params.json
    (None when they are missing or unreadable)."""
    try:
        measured = json.loads((folder / "measurements.json").read_text())
        params = json.loads((folder / "params.json").read_text())
        stages = params["stages"]
        return SubjectResult(
            name,
            SubjectStatus(params["status"]),
            params["message"],
            {k: float(measured[k]) for k in MEASUREMENT_KEYS if k in measured},
            final_cost=float(stages[-1]["cost"]) if stages else math.nan,
            iterations=sum(int(s["iterations"]) for s in stages),
            seconds=float(params.get("seconds", 0.0)),
            resumed=True,
        )
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return None


def clear_outputs(folder: Path) -> None:
    """Remove what a run wrote into a subject folder, the done marker first (other files are
    left alone).

    Raises:
        OutputError: a file cannot be removed.
    """
    if not folder.is_dir():
        return
    remove_files(folder / f for f in OUTPUT_FILES)
    remove_files(sorted(folder.glob("overlay_pose*.png")))
    remove_files(sorted(folder.glob("meshes/*.obj")))
    remove_temporary(folder)
    remove_temporary(folder / "meshes")
