"""Wire the stages for a dataset; the only place a config enters the library.

Per subject: validate the folder and segment the six posture images against the background
frames. Then, in batches of ``fit.batch_size`` subjects: build the person contours and
distance maps, start from the template at the nominal postures, and run the fit's stages
(batched Levenberg–Marquardt with the autograd Jacobian, or the paper's rendered-contour
MINPACK baseline with ``solver.jacobian: numeric``). Each subject gets measurements.json,
params.json, the fitted model (URDF + meshes, GLB/OBJ) and overlays of the fitted model
contour (green) on the person contour (magenta) for every posture; the run gets summary.csv,
the resolved config and TensorBoard event files under ``tb/``.

One bad subject never stops the others: it gets ``status = failed`` and the reason, and what
finished is on disk (a rerun resumes, skipping finished subjects).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchfit.body.measure import measure_model
from torchfit.body.model import BodyModel
from torchfit.body.postures import POSTURES
from torchfit.camera import Camera, stack_cameras
from torchfit.config import Config, save_config
from torchfit.errors import DataError, SegmentationError, TorchfitError
from torchfit.fitting import PersonData, SilhouetteFit, person_data_from_masks
from torchfit.image.background import fit_background
from torchfit.image.segment import segment
from torchfit.io.dataset import Subject, load_dataset
from torchfit.io.export import export_mesh, export_urdf, write_json
from torchfit.io.images import load_frames
from torchfit.measurements import MEASUREMENT_KEYS
from torchfit.render import draw_label, draw_polyline, outer_outlines
from torchfit.solver import keep_heap

__all__ = ["SubjectResult", "run", "segment_subject", "person_data", "fit_batch", "write_summary"]

log = logging.getLogger(__name__)

_DONE_FILES = ("measurements.json", "params.json")
_FAILED = {"NONFINITE", "LINALG"}


@dataclass
class SubjectResult:
    """Outcome of one subject (a row of summary.csv)."""

    name: str
    status: str  # "ok", "poor_fit" (fitted, but far from the person's contour), "failed"
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


@dataclass
class _Prepared:
    subject: Subject
    images: torch.Tensor  # (6, 3, H, W) RGB in [0, 1]
    masks: torch.Tensor  # (6, H, W) bool
    shadow: torch.Tensor  # (6, H, W) bool, pixels the shadow test removed
    seconds: float


def segment_subject(
    subject: Subject, config: Config
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Segment a subject's six posture images.

    Returns:
        images (6, 3, H, W) in [0, 1], silhouettes (6, H, W) bool and the pixels the shadow
        test removed (6, H, W) bool (:attr:`torchfit.image.SegmentationResult.shadow`).

    Raises:
        DataError: invalid subject folder; SegmentationError: no person in a posture image.
    """
    if subject.problems:
        raise DataError("; ".join(subject.problems))
    size = subject.camera.image_size
    background, _ = load_frames(subject.background, size=size)
    images, _ = load_frames(subject.poses, size=size)
    seg = segment(images, fit_background(background, config.segmentation), config.segmentation)
    missing = [
        f"pose{i + 1} ({subject.poses[i].name})"
        for i, ok in enumerate(seg.found.tolist())
        if not ok
    ]
    if missing:
        raise SegmentationError(f"no person found in {', '.join(missing)}")
    return images, seg.masks[:, 0], seg.shadow[:, 0]


def person_data(
    config: Config,
    masks: torch.Tensor,
    shadow: torch.Tensor,
    cameras: Camera,
    dtype: torch.dtype,
) -> PersonData:
    """The person side of the fit from segmented postures (B, J, H, W), as ``config`` says
    (distance transform, contour stride, shadow pixels as uncertain)."""
    use_shadow = config.fit.ignore_shadow and config.segmentation.shadow_test
    return person_data_from_masks(
        masks,
        cameras,
        config.segmentation.distance,
        config.fit.contour_stride,
        dtype,
        shadow if use_shadow else None,
        config.fit.shadow_margin_px,
    )


def _overlay(
    image: np.ndarray,
    person: np.ndarray,
    model_mask: np.ndarray,
    label: str,
    uncertain: np.ndarray | None = None,
):
    """RGB overlay: uncertain pixels tinted yellow, person contour magenta, model contour
    green, a label."""

    out = image.copy()
    if uncertain is not None and uncertain.any():
        tint = np.array([255, 220, 0], dtype=np.float32)
        out[uncertain] = (0.5 * out[uncertain] + 0.5 * tint).astype(np.uint8)
    for c in outer_outlines(person):
        draw_polyline(out, c, (255, 0, 255), thickness=2)
    for c in outer_outlines(model_mask):
        draw_polyline(out, c, (0, 200, 0), thickness=2)
    draw_label(out, label, (10, 28), 0.8)
    return out


def _status_name(code: int) -> str:
    from torchfit.solver import LMStatus

    try:
        return LMStatus(code).name
    except ValueError:
        return str(code)


def fit_batch(
    prepared: list[_Prepared],
    model: BodyModel,
    config: Config,
    run_dir: Path,
    tb=None,
) -> list[SubjectResult]:
    """Fit a batch of segmented subjects and write their outputs.

    Args:
        prepared: the segmented subjects.
        model: the body model.
        config: the resolved config.
        run_dir: the run folder (subject outputs go to ``run_dir / name``).
        tb: optional TensorBoard logger (:class:`torchfit.tb_logging.TensorBoardCallback`).
    """

    start = time.perf_counter()
    names = [p.subject.name for p in prepared]
    used = [j - 1 for j in config.fit.poses]  # the fitted postures, in fit.poses order
    masks = torch.stack([p.masks[used] for p in prepared])
    cameras = stack_cameras([p.subject.camera for p in prepared])
    shadow = torch.stack([p.shadow[used] for p in prepared])
    person = person_data(config, masks, shadow, cameras, model.dtype)
    fit = SilhouetteFit(model, person, config.fit, config.model)
    starts = None
    if config.fit.initial_guess == "parts":
        from torchfit.initial_guess import parts_start

        images = torch.stack([p.images[used] for p in prepared])
        x, starts = parts_start(fit, masks, images, config.parts)
        for name, info in zip(names, starts, strict=True):
            if info.message:
                log.info("%s: initial guess %s: %s", name, info.source, info.message)
    else:
        x = fit.initial_params()
    solver_cfg = config.solver
    stages_out: list[list[dict]] = [[] for _ in prepared]
    for si, stage in enumerate(config.fit.stages):
        options = solver_cfg.lm_options(stage.max_iter or solver_cfg.max_iter)
        tag = f"stage{si + 1}_{stage.name}"
        if solver_cfg.jacobian == "numeric":
            from torchfit.baseline import minpack_stage

            x, results = minpack_stage(fit, x, stage, options)
            per = [
                (int(r.status[0]), float(r.cost[0]), int(r.nfev[0]), r.message[0]) for r in results
            ]
        else:
            callback = None
            if tb is not None:
                from torchfit.tb_logging import TensorBoardCallback

                callback = TensorBoardCallback(tb.writer, tag, names, log_every=1)
            x, res = fit.solve_stage(x, stage, options, callback=callback)
            per = [
                (int(res.status[i]), float(res.cost[i]), int(res.n_iter[i]), res.message[i])
                for i in range(len(prepared))
            ]
        for i, (code, cost, iters, message) in enumerate(per):
            stages_out[i].append(
                {
                    "stage": stage.name,
                    "status": _status_name(code),
                    "message": message,
                    "cost": cost,
                    "iterations": iters,
                }
            )
        if any(_status_name(p[0]) in _FAILED for p in per):
            log.warning("%s: %s", tag, [p[3] for p in per])
    seconds = (time.perf_counter() - start) / len(prepared)

    # outputs
    group = x[:, : fit.num_scale_params].reshape(-1, model.num_groups, 3)
    scales = model.expand_scales(group)
    measures = measure_model(model, scales)
    rows = torch.arange(len(prepared))
    selections = fit.select(x)
    final = fit.residual(x, selections)
    results = []
    for i, prep in enumerate(prepared):
        folder = run_dir / prep.subject.name
        folder.mkdir(parents=True, exist_ok=True)
        stage_status = [s["status"] for s in stages_out[i]]
        failed = any(s in _FAILED for s in stage_status) or not math.isfinite(
            stages_out[i][-1]["cost"]
        )
        quality, offset = {}, 0
        for k, j in enumerate(fit.poses):
            n = person.valid[k].shape[1]
            quality[f"pose{j}"] = {
                "e_P_rms_px": float(final[i, offset : offset + n].norm()),
                "e_M_px": float(final[i, offset + n]),
            }
            offset += n + 1
        worst = max(quality, key=lambda key: quality[key]["e_M_px"])
        message = stages_out[i][-1]["message"]
        if failed:
            status = "failed"
        elif quality[worst]["e_M_px"] > config.fit.max_contour_rms_px:
            status = "poor_fit"
            message = (
                f"model contour {quality[worst]['e_M_px']:.1f} px (RMS) from the "
                f"person's in {worst}: check the segmentation in the overlays"
            )
        else:
            status = "ok"
        measurements = {k: float(v[i]) for k, v in measures.items()}
        poses = {}
        for j in fit.poses:
            s_, angles, rot, trans = fit.pose_state(x[i : i + 1], j, rows[i : i + 1])
            poses[f"pose{j}"] = {
                "name": POSTURES[j - 1].name,
                "joint_angles": dict(zip(model.dof_names, angles[0].tolist(), strict=True)),
                "free_joints": [model.dof_names[d] for d in fit.pose_joints[j]],
                "root_translation_xy": trans[0, :2],
                "root_rotation": rot[0],
                "offsets": dict(
                    zip(
                        ("tx", "ty", "yaw", "roll", "pitch"),
                        x[i, fit.pose_slices[j]][-5:].tolist(),
                        strict=True,
                    )
                ),
            }
            if config.output.overlays:
                import cv2

                image = (prep.images[j - 1].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
                overlay = _overlay(
                    image,
                    prep.masks[j - 1].numpy(),
                    selections[j].masks[i],
                    f"{prep.subject.name} pose{j} {POSTURES[j - 1].name}",
                    prep.shadow[j - 1].numpy() if fit.person.uncertain is not None else None,
                )
                cv2.imwrite(str(folder / f"overlay_pose{j}.png"), overlay[:, :, ::-1])
                if tb is not None:
                    tb.add_image(f"overlay/{prep.subject.name}/pose{j}", overlay)
        if tb is not None:
            for pose, values in quality.items():
                for key, value in values.items():
                    tb.add_scalar(f"residual/{prep.subject.name}/{pose}_{key}", value, 0)
        export_urdf(model, scales[i], folder)
        neutral = model(
            scales[i : i + 1], **{k: v for k, v in model.zeros(1).items() if k != "scales"}
        )
        export_mesh(neutral.vertices[0], model.faces, folder / f"model.{config.output.mesh_format}")
        write_json(
            folder / "params.json",
            {
                "template": model.template.name,
                "status": status,
                "message": message,
                "method": "minpack_rendered" if solver_cfg.jacobian == "numeric" else "autograd_lm",
                "group_scales": {
                    g: group[i, gi] for gi, g in enumerate(model.template.scale_groups)
                },
                "segment_scales": dict(
                    zip(model.template.segments, scales[i].tolist(), strict=True)
                ),
                "initial_guess": starts[i].to_dict() if starts else {"source": "template"},
                "poses": poses,
                "stages": stages_out[i],
            },
        )
        write_json(folder / "measurements.json", {**measurements, "status": status})
        iterations = sum(s["iterations"] for s in stages_out[i])
        results.append(
            SubjectResult(
                prep.subject.name,
                status,
                message,
                measurements,
                final_cost=stages_out[i][-1]["cost"],
                iterations=iterations,
                seconds=seconds + prep.seconds,
            )
        )
    return results


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
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(SubjectResult("", "").row()))
        writer.writeheader()
        writer.writerows(r.row() for r in results)


def run(
    config: Config,
    run_dir: Path,
    progress: Callable[[int], object] | None = None,
) -> list[SubjectResult]:
    """Run a whole dataset: the resolved config, per-subject outputs and summary.csv.

    Args:
        config: the resolved configuration (``data.root`` must be set).
        run_dir: the run folder.
        progress: optional factory ``total -> bar`` with ``update(n)`` and ``close()``
            (e.g. ``lambda n: tqdm(total=n)``).

    Returns:
        One :class:`SubjectResult` per subject, failed ones included, in dataset order.
    """
    if not config.data.root:
        raise DataError("data.root is not set: pass --data DIR or set data.root in the config")
    if config.run.num_threads:
        torch.set_num_threads(config.run.num_threads)
    if config.run.keep_heap and not keep_heap():
        log.warning("run.keep_heap: the C library is not glibc; the setting has no effect")
    run_dir.mkdir(parents=True, exist_ok=True)
    save_config(config, run_dir / "config.yaml")
    subjects = load_dataset(config.data.root, config.data.subjects)
    if not subjects:
        raise DataError(f"no subject folders found in {config.data.root}")
    dtype = torch.float64 if config.run.dtype == "float64" else torch.float32
    model = BodyModel(config.model.template, device=config.run.device, dtype=dtype)
    bar = progress(len(subjects)) if progress else None
    done: dict[str, SubjectResult] = {}
    todo: list[Subject] = []
    for subject in subjects:
        previous = _resumed(subject, run_dir / subject.name) if config.run.resume else None
        if previous is not None:
            done[subject.name] = previous
            if bar:
                bar.update(1)
        else:
            todo.append(subject)
    tb = None
    if config.output.tensorboard and todo:
        from torchfit.tb_logging import TensorBoardCallback

        tb = TensorBoardCallback(run_dir / "tb", "fit")

    def finish(result: SubjectResult) -> None:
        done[result.name] = result
        if bar:
            bar.update(1)
        write_summary([done[s.name] for s in subjects if s.name in done], run_dir / "summary.csv")

    try:
        for start in range(0, len(todo), config.fit.batch_size):
            prepared = []
            for subject in todo[start : start + config.fit.batch_size]:
                t0 = time.perf_counter()
                try:
                    images, masks, shadow = segment_subject(subject, config)
                    prepared.append(
                        _Prepared(subject, images, masks, shadow, time.perf_counter() - t0)
                    )
                except (TorchfitError, OSError) as exc:
                    log.error("%s: %s", subject.name, exc)
                    finish(SubjectResult(subject.name, "failed", str(exc)))
            if not prepared:
                continue
            try:
                results = fit_batch(prepared, model, config, run_dir, tb)
            except (TorchfitError, RuntimeError) as exc:
                log.error("batch %s failed: %s", [p.subject.name for p in prepared], exc)
                results = [
                    SubjectResult(p.subject.name, "failed", f"fit failed: {exc}") for p in prepared
                ]
            for result in results:
                finish(result)
    finally:
        if tb is not None:
            tb.close()
        if bar:
            bar.close()
    ordered = [done[s.name] for s in subjects]
    write_summary(ordered, run_dir / "summary.csv")
    return ordered
