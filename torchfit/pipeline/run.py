"""The fit run over a dataset: the only place where the config meets the fit.

Per subject: validate the folder and segment the six posture images against the background
frames (:mod:`torchfit.pipeline.prepare`). Then, in batches of ``fit.batch_size`` subjects:
build the person data, start from the template (or the automatic guess), run the stages
(:mod:`torchfit.pipeline.stages`), judge each subject (:mod:`torchfit.pipeline.judge`) and
write its outputs (:mod:`torchfit.pipeline.outputs`); the run gets summary.csv, the resolved
config and TensorBoard event files under ``tb/``.

One bad subject never stops the others: it gets ``status = failed`` and the reason, and what
finished is on disk. Each finished subject's folder ends with ``fingerprint.json``
(:mod:`torchfit.pipeline.fingerprint`); a rerun keeps the subjects whose fingerprint is
unchanged and refits the others. Every file is written atomically, so a run killed at any
moment and run again ends as a clean run would. A file that cannot be written stops the run
with :class:`~torchfit.errors.OutputError` (what finished before stays complete).
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
from torchfit.config.loader import config_to_yaml
from torchfit.config.schema import Config
from torchfit.errors import ConfigError, DataError, OutputError, TorchfitError
from torchfit.fit.bends import BendFit
from torchfit.fit.prior import KnownFacts, PriorFit, load_prior
from torchfit.fit.problem import SilhouetteFit
from torchfit.io.dataset import Subject, load_dataset
from torchfit.io.export import write_json
from torchfit.io.files import make_dirs, remove_temporary, write_atomic
from torchfit.pipeline.fingerprint import (
    Fingerprint,
    config_digest,
    read_fingerprint,
    template_digest,
    write_fingerprint,
)
from torchfit.pipeline.judge import judge
from torchfit.pipeline.outputs import (
    SubjectResult,
    clear_outputs,
    params_document,
    result_from_disk,
    write_model,
    write_overlays,
    write_summary,
)
from torchfit.pipeline.prepare import PreparedSubject, person_data, prepare_subject
from torchfit.pipeline.runtime import apply_runtime, torch_dtype
from torchfit.pipeline.stages import check_names, run_stages, start_params
from torchfit.status import SubjectStatus

__all__ = ["run", "fit_batch", "fit_subjects", "batches", "build_problem"]

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
    person = person_data(config, masks, shadow, cameras, model.dtype).to(model.device)
    fit = build_problem(model, person, config, [p.subject.facts for p in prepared])
    x, starts = start_params(fit, config, masks, [p.float_images(used) for p in prepared])
    if starts is not None:
        for name, info in zip(names, starts, strict=True):
            if info.message:
                log.info("%s: initial guess %s: %s", name, info.source, info.message)
    x, records = run_stages(fit, x, config, names, tb, stage_progress)
    return fit, x, starts, records


def build_problem(model: BodyModel, person, config: Config, facts: list[dict]) -> SilhouetteFit:
    """The batch's problem: with the population prior and the known facts where the config
    weighs the prior or a subject has ``subject.yaml`` facts.

    Args:
        model: the body model.
        person: the batch's :class:`torchfit.fit.PersonData` (B subjects).
        config: the run's config (``model`` bounds, ``fit`` options and prior).
        facts: one ``subject.yaml`` dict per subject (empty where none).

    Returns:
        a :class:`torchfit.fit.SilhouetteFit`; a :class:`torchfit.fit.prior.PriorFit`
        when the prior is weighed or some subject has facts; a
        :class:`torchfit.fit.bends.BendFit` when the bent-joint marks are weighed (then
        ``person.silhouettes`` must hold the marked postures' silhouettes).
    """
    bounds = (config.model.scale_min, config.model.scale_max)
    options = config.fit.prior
    bends = config.fit.bends
    if options.weight == 0 and options.pose_weight == 0 and bends.weight == 0 and not any(facts):
        return SilhouetteFit(model, person, config.fit, bounds)
    prior = load_prior(options.name) if options.weight > 0 else None
    known = [KnownFacts(**f) for f in facts]
    if bends.weight > 0:
        return BendFit(model, person, config.fit, bounds, prior, options, known, bends)
    return PriorFit(model, person, config.fit, bounds, prior, options, known)


def facts_record(fit: SilhouetteFit, i: int) -> dict:
    """params.json's record of the prior and the known facts of subject ``i``."""
    if not isinstance(fit, PriorFit):
        return {"prior": None, "posture_prior": None, "known_facts": {}, "facts_used": {}}
    opts = fit.prior_options
    posture = None
    if fit.residual_layout.num_pose_prior:
        posture = {
            "weight": opts.pose_weight,
            "sigma_deg": opts.pose_sigma_deg,
            "joints": list(opts.pose_joints),
        }
    facts = fit.facts[i]
    used: dict = {}
    if facts.height_m is not None:
        used["height_m"] = {
            "value": facts.height_m,
            "tolerance_m": fit.prior_options.height_tolerance_m,
        }
    prior = None
    if fit.prior is not None:
        component = fit.prior_components[i]
        prior = {"name": fit.prior.name, "weight": fit.prior_options.weight, "component": component}
        if facts.sex is not None:
            used["sex"] = f"prior component {component!r}"
    return {
        "prior": prior,
        "posture_prior": posture,
        "known_facts": facts.to_dict(),
        "facts_used": used,
    }


def fit_batch(
    prepared: list[PreparedSubject],
    model: BodyModel,
    config: Config,
    run_dir: Path,
    tb=None,
    stage_progress: Callable[[str, int], object] | None = None,
    fingerprints: dict[str, Fingerprint] | None = None,
) -> list[SubjectResult]:
    """Fit a batch of segmented subjects and write their outputs, ``fingerprint.json`` last.

    Args:
        prepared: the segmented subjects.
        model: the body model.
        config: the resolved config.
        run_dir: the run folder (subject outputs go to ``run_dir / name``).
        tb: optional TensorBoard logger
            (:class:`torchfit.pipeline.tensorboard.TensorBoardCallback`).
        stage_progress: optional per-stage iteration bar factory
            (:func:`torchfit.pipeline.stages.run_stages`).
        fingerprints: subject name -> its :class:`Fingerprint` (computed when missing).

    Raises:
        OutputError: a file cannot be written (subjects written before are complete).
    """
    fingerprints = dict(fingerprints or {})
    run_fp = None
    for prep in prepared:
        if prep.subject.name not in fingerprints:
            if run_fp is None:
                run_fp = Fingerprint(config_digest(config), template_digest(model.template))
            fingerprints[prep.subject.name] = run_fp.for_subject(prep.subject)
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
        if not run_dir.is_dir():  # e.g. a vanished mount: do not write beside it
            raise OutputError(f"cannot write {folder}: the run folder {run_dir} is gone")
        clear_outputs(folder)  # fingerprint.json first: the folder is not finished until the end
        make_dirs(folder)
        # the residual is in reference pixels (fit.reference_px_per_m); quality in the image's
        scale = float(fit.image_scale[i])
        quality = {
            f"pose{j}": {"e_P_rms_px": e_p / scale, "e_M_px": e_m / scale}
            for j, (e_p, e_m) in fit.residual_layout.per_pose_quality(final[i]).items()
        }
        limit = config.fit.max_contour_rms_px / scale
        status, message = judge(records[i], quality, limit, prep.flags)
        measurements = {k: float(v[i]) for k, v in measures.items()}
        bends = fit.mark_record(x, selections, i) if isinstance(fit, BendFit) else None
        if config.output.overlays:
            write_overlays(folder, prep, fit, selections, i, tb, bends)
        if tb is not None:
            for pose, values in quality.items():
                for key, value in values.items():
                    tb.add_scalar(f"residual/{name}/{pose}_{key}", value, 0)
        write_model(model, scales[i], folder, config.output.mesh_format)
        start_info = starts[i].to_dict() if starts else {"source": "template"}
        document = params_document(
            fit,
            x,
            i,
            scales[i],
            status,
            message,
            config.fit.method,
            start_info,
            records[i],
            seconds + prep.seconds,
        )
        document.update(facts_record(fit, i))
        if bends is not None:
            document["bends"] = bends
        document["segmentation_notes"] = prep.notes + prep.flags
        write_json(folder / "params.json", document)
        write_json(folder / "measurements.json", {**measurements, "status": str(status)})
        write_fingerprint(folder, fingerprints[name])
        result = result_from_disk(name, folder)
        if result is None:  # the files just written cannot be read back
            raise OutputError(f"cannot read back the outputs written to {folder}")
        result.resumed = False
        results.append(result)
    return results


def batches(subjects: list[Subject], size: int) -> list[list[Subject]]:
    """``subjects`` in batches of ``size``, one image size per batch (a batch stacks its
    images): the subjects grouped by their camera's image size, the groups in the order of
    their first subject and each cut into consecutive batches (a group's last may be smaller).
    A dataset of one image size gives consecutive batches in its own order; a subject's result
    does not depend on its batch. Invalid subjects (``subject.problems``) are batched apart,
    so that they take no valid subject's place in a batch."""
    groups: dict[tuple[int, int] | None, list[Subject]] = {}
    for subject in subjects:
        size_of = None if not subject.ok else tuple(subject.camera.image_size)
        groups.setdefault(size_of, []).append(subject)
    return [
        group[start : start + size]
        for group in groups.values()
        for start in range(0, len(group), size)
    ]


def fit_subjects(
    subjects: list[Subject],
    model: BodyModel,
    config: Config,
    run_dir: Path,
    tb=None,
    stage_progress: Callable[[str, int], object] | None = None,
    fingerprints: dict[str, Fingerprint] | None = None,
) -> list[SubjectResult]:
    """Segment and fit one batch of subjects and write their outputs under ``run_dir``.

    A subject that cannot be read or segmented fails alone; a batch whose fit fails fails all
    of its subjects (the reason in each result). This is the work of one task of any executor.

    Returns:
        One :class:`SubjectResult` per subject, failed ones included (order: the failures of
        preparation first, then the fitted subjects in batch order).

    Raises:
        OutputError: a file cannot be written.
    """
    results = []
    prepared = []
    for subject in subjects:
        try:
            prepared.append(prepare_subject(subject, config))
        except (TorchfitError, OSError) as exc:
            log.error("%s: %s", subject.name, exc)
            clear_outputs(run_dir / subject.name)
            results.append(SubjectResult(subject.name, SubjectStatus.FAILED, str(exc)))
    if not prepared:
        return results
    try:
        return results + fit_batch(
            prepared, model, config, run_dir, tb, stage_progress, fingerprints
        )
    except OutputError:
        raise
    except (TorchfitError, RuntimeError) as exc:
        log.error("batch %s failed: %s", [p.subject.name for p in prepared], exc)
        for p in prepared:
            clear_outputs(run_dir / p.subject.name)
            results.append(
                SubjectResult(p.subject.name, SubjectStatus.FAILED, f"fit failed: {exc}")
            )
    return results


def _kept(
    subjects: list[Subject], run_fp: Fingerprint, run_dir: Path, resume: bool
) -> tuple[dict[str, SubjectResult], dict[str, Fingerprint]]:
    """The subjects an earlier run finished with today's fingerprint (their results), and the
    fingerprint of every other readable subject."""
    kept: dict[str, SubjectResult] = {}
    fingerprints: dict[str, Fingerprint] = {}
    for subject in subjects:
        if not subject.ok:
            continue
        try:
            fingerprint = run_fp.for_subject(subject)
        except DataError as exc:  # unreadable inputs: fitting it reports the problem
            log.debug("%s: %s", subject.name, exc)
            continue
        fingerprints[subject.name] = fingerprint
        folder = run_dir / subject.name
        previous = read_fingerprint(folder)
        change = fingerprint.changes(previous) if resume else "run.resume is false"
        if not change:
            result = result_from_disk(subject.name, folder)
            if result is not None:
                kept[subject.name] = result
                continue
            change = "its outputs cannot be read"
        if previous is not None:
            log.info("%s: refitting (%s)", subject.name, change)
    return kept, fingerprints


def run(
    config: Config,
    run_dir: Path,
    progress: Callable[[int], object] | None = None,
    stage_progress: Callable[[str, int], object] | None = None,
) -> list[SubjectResult]:
    """Run a whole dataset: the resolved config, per-subject outputs and summary.csv.

    Subjects whose outputs an earlier run finished with the same fingerprint are kept
    (``run.resume``, :mod:`torchfit.pipeline.fingerprint`); the run folder and its
    ``config.yaml`` are written only once the dataset and the template have loaded.

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

    Raises:
        ConfigError: ``data.root`` is not set; DataError: the dataset is missing or empty;
        ModelError: the template cannot be loaded; OutputError: the run folder cannot be
        written (subjects finished before are complete on disk).
    """
    if not config.data.root:
        raise ConfigError("data.root is not set: pass --data DIR or set data.root in the config")
    if config.run.executor == "ray":
        from torchfit.pipeline.ray_executor import require_ray

        require_ray()
    apply_runtime(config.run)
    subjects = load_dataset(config.data.root, config.data.subjects, config.segmentation.method)
    if not subjects:
        raise DataError(f"no subject folders found in {config.data.root}")
    # with Ray the workers fit: the driver's model (fingerprints only) stays on the CPU
    device = config.run.device if config.run.executor == "local" else "cpu"
    model = BodyModel(config.model.template, device=device, dtype=torch_dtype(config.run.dtype))
    check_names(model, config)  # a name the template or a prior lacks stops the run
    run_fp = Fingerprint(config_digest(config), template_digest(model.template))
    done, fingerprints = _kept(subjects, run_fp, run_dir, config.run.resume)
    todo = [s for s in subjects if s.name not in done]
    session = None
    if config.run.executor == "ray" and todo:  # connect before writing anything
        from torchfit.pipeline.ray_executor import start_ray

        session = start_ray(config.run)

    try:
        make_dirs(run_dir)
        remove_temporary(run_dir)
        write_atomic(run_dir / "config.yaml", config_to_yaml(config))
    except OutputError:
        if session is not None:
            session.close()
        raise
    bar = progress(len(subjects)) if progress else None
    if bar and done:
        bar.update(len(done))
    tb = None
    if config.output.tensorboard and todo and config.run.executor == "local":
        from torchfit.pipeline.tensorboard import TensorBoardCallback

        tb = TensorBoardCallback(run_dir / "tb", "fit")

    def finish(result: SubjectResult) -> None:
        done[result.name] = result
        if bar:
            bar.update(1)
        write_summary([done[s.name] for s in subjects if s.name in done], run_dir / "summary.csv")

    try:
        if session is not None:
            from torchfit.pipeline.ray_executor import run_on_ray

            run_on_ray(session, todo, config, run_dir, fingerprints, finish)
        else:
            for batch in batches(todo, config.fit.batch_size):
                for result in fit_subjects(
                    batch, model, config, run_dir, tb, stage_progress, fingerprints
                ):
                    finish(result)
    finally:
        if session is not None:
            session.close()
        if tb is not None:
            tb.close()
        if bar:
            bar.close()
    ordered = [done[s.name] for s in subjects]
    write_summary(ordered, run_dir / "summary.csv")
    return ordered
