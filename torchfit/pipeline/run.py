"""The fit run over a dataset: the only place where the config meets the fit.

Per subject: validate the folder and segment the six posture images against the background
frames (:mod:`torchfit.pipeline.prepare`). Then, in batches of ``fit.batch_size`` subjects:
build the person data, start from the template (or the automatic guess), run the stages
(:mod:`torchfit.pipeline.stages`), judge each subject (:mod:`torchfit.pipeline.judge`) and
write its outputs (:mod:`torchfit.pipeline.outputs`); the run gets summary.csv, the resolved
config and TensorBoard event files under ``tb/``.

One bad subject never stops the others: it gets ``status = failed`` and the reason, and what
finished is on disk (a rerun resumes, skipping finished subjects).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path

import torch

from torchfit.body.measure import measure_model
from torchfit.body.model import BodyModel
from torchfit.camera import stack_cameras
from torchfit.config.loader import save_config
from torchfit.config.schema import Config
from torchfit.errors import DataError, TorchfitError
from torchfit.fit.problem import SilhouetteFit
from torchfit.io.dataset import Subject, load_dataset
from torchfit.io.export import write_json
from torchfit.pipeline.judge import judge
from torchfit.pipeline.outputs import (
    SubjectResult,
    params_document,
    resumed_result,
    write_model,
    write_overlays,
    write_summary,
)
from torchfit.pipeline.prepare import PreparedSubject, person_data, prepare_subject
from torchfit.pipeline.runtime import apply_runtime, torch_dtype
from torchfit.pipeline.stages import run_stages, start_params
from torchfit.status import SubjectStatus

__all__ = ["run", "fit_batch"]

log = logging.getLogger(__name__)


def _fit(
    prepared: list[PreparedSubject], model: BodyModel, config: Config, tb=None, stage_progress=None
):
    """Build the batch's problem, start it and run the stages."""
    names = [p.subject.name for p in prepared]
    used = [j - 1 for j in config.fit.poses]  # the fitted postures, in fit.poses order
    masks = torch.stack([p.masks[used] for p in prepared])
    shadow = torch.stack([p.shadow[used] for p in prepared])
    cameras = stack_cameras([p.subject.camera for p in prepared])
    person = person_data(config, masks, shadow, cameras, model.dtype)
    fit = SilhouetteFit(model, person, config.fit, (config.model.scale_min, config.model.scale_max))
    images = torch.stack([p.images[used] for p in prepared])
    x, starts = start_params(fit, config, masks, images)
    if starts is not None:
        for name, info in zip(names, starts, strict=True):
            if info.message:
                log.info("%s: initial guess %s: %s", name, info.source, info.message)
    x, records = run_stages(fit, x, config, names, tb, stage_progress)
    return fit, x, starts, records


def fit_batch(
    prepared: list[PreparedSubject],
    model: BodyModel,
    config: Config,
    run_dir: Path,
    tb=None,
    stage_progress: Callable[[str, int], object] | None = None,
) -> list[SubjectResult]:
    """Fit a batch of segmented subjects and write their outputs.

    Args:
        prepared: the segmented subjects.
        model: the body model.
        config: the resolved config.
        run_dir: the run folder (subject outputs go to ``run_dir / name``).
        tb: optional TensorBoard logger
            (:class:`torchfit.pipeline.tensorboard.TensorBoardCallback`).
        stage_progress: optional per-stage iteration bar factory
            (:func:`torchfit.pipeline.stages.run_stages`).
    """
    start = time.perf_counter()
    fit, x, starts, records = _fit(prepared, model, config, tb, stage_progress)
    seconds = (time.perf_counter() - start) / len(prepared)

    scales = model.expand_scales(fit.layout.group_scales(x))
    measures = measure_model(model, scales)
    selections = fit.select(x)
    final = fit.residual(x, selections)
    results = []
    for i, prep in enumerate(prepared):
        name = prep.subject.name
        folder = run_dir / name
        folder.mkdir(parents=True, exist_ok=True)
        quality = {
            f"pose{j}": {"e_P_rms_px": e_p, "e_M_px": e_m}
            for j, (e_p, e_m) in fit.residual_layout.per_pose_quality(final[i]).items()
        }
        status, message = judge(records[i], quality, config.fit.max_contour_rms_px)
        measurements = {k: float(v[i]) for k, v in measures.items()}
        if config.output.overlays:
            write_overlays(folder, prep, fit, selections, i, tb)
        if tb is not None:
            for pose, values in quality.items():
                for key, value in values.items():
                    tb.add_scalar(f"residual/{name}/{pose}_{key}", value, 0)
        write_model(model, scales[i], folder, config.output.mesh_format)
        start_info = starts[i].to_dict() if starts else {"source": "template"}
        write_json(
            folder / "params.json",
            params_document(
                fit, x, i, scales[i], status, message, config.fit.method, start_info, records[i]
            ),
        )
        write_json(folder / "measurements.json", {**measurements, "status": str(status)})
        results.append(
            SubjectResult(
                name,
                status,
                message,
                measurements,
                final_cost=records[i][-1].cost,
                iterations=sum(s.iterations for s in records[i]),
                seconds=seconds + prep.seconds,
            )
        )
    return results


def run(
    config: Config,
    run_dir: Path,
    progress: Callable[[int], object] | None = None,
    stage_progress: Callable[[str, int], object] | None = None,
) -> list[SubjectResult]:
    """Run a whole dataset: the resolved config, per-subject outputs and summary.csv.

    Args:
        config: the resolved configuration (``data.root`` must be set).
        run_dir: the run folder.
        progress: optional factory ``total -> bar`` with ``update(n)`` and ``close()``
            (e.g. ``lambda n: tqdm(total=n)``), advanced per finished subject.
        stage_progress: optional factory ``(description, total) -> bar`` for the current
            batch's stages, advanced per solver iteration with the cost
            (e.g. ``lambda d, n: tqdm(total=n, desc=d, leave=False)``).

    Returns:
        One :class:`SubjectResult` per subject, failed ones included, in dataset order.
    """
    if not config.data.root:
        raise DataError("data.root is not set: pass --data DIR or set data.root in the config")
    apply_runtime(config.run)
    run_dir.mkdir(parents=True, exist_ok=True)
    save_config(config, run_dir / "config.yaml")
    subjects = load_dataset(config.data.root, config.data.subjects)
    if not subjects:
        raise DataError(f"no subject folders found in {config.data.root}")
    model = BodyModel(
        config.model.template, device=config.run.device, dtype=torch_dtype(config.run.dtype)
    )
    bar = progress(len(subjects)) if progress else None
    done: dict[str, SubjectResult] = {}
    todo: list[Subject] = []
    for subject in subjects:
        previous = resumed_result(subject, run_dir / subject.name) if config.run.resume else None
        if previous is not None:
            done[subject.name] = previous
            if bar:
                bar.update(1)
        else:
            todo.append(subject)
    tb = None
    if config.output.tensorboard and todo:
        from torchfit.pipeline.tensorboard import TensorBoardCallback

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
                try:
                    prepared.append(prepare_subject(subject, config))
                except (TorchfitError, OSError) as exc:
                    log.error("%s: %s", subject.name, exc)
                    finish(SubjectResult(subject.name, SubjectStatus.FAILED, str(exc)))
            if not prepared:
                continue
            try:
                results = fit_batch(prepared, model, config, run_dir, tb, stage_progress)
            except (TorchfitError, RuntimeError) as exc:
                log.error("batch %s failed: %s", [p.subject.name for p in prepared], exc)
                results = [
                    SubjectResult(p.subject.name, SubjectStatus.FAILED, f"fit failed: {exc}")
                    for p in prepared
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
