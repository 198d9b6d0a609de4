"""The Ray executor of a fit run (``run.executor: ray``): batches of subjects as Ray tasks.

The driver (:func:`torchfit.pipeline.run`) decides what to fit (resume, fingerprints) and
cuts the subjects into batches of ``fit.batch_size``, as the local executor does. Each batch
becomes one Ray task that asks for ``threads`` CPUs (or one GPU with ``run.device: cuda``),
sets its own torch thread count, segments and fits its subjects
(:func:`torchfit.pipeline.run.fit_subjects`) into a temporary folder of its node and returns
the files it wrote. The driver writes them into the run folder (``fingerprint.json`` of each
subject last, as a local run does) and keeps summary.csv; the tasks' TensorBoard event files
go to the run's one ``tb/`` folder. So only the driver's machine needs the run folder; every
node reads the dataset at the same path (a shared filesystem).

A worker that dies has its task run again (Ray's task retries, :data:`MAX_RETRIES`); a
subject that fails is a failed result, as in a local run. The batches are the local run's
batches, so the measurements are the local run's (to the last digits where the thread count is
the same).

Ray is imported only here, and only when the executor is used (``pip install "torchfit[ray]"``).
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from torchfit.config.schema import Config, RunConfig
from torchfit.errors import ConfigError, OutputError
from torchfit.io.dataset import Subject
from torchfit.io.files import make_dirs, write_atomic
from torchfit.pipeline.fingerprint import FINGERPRINT_FILE, Fingerprint
from torchfit.pipeline.outputs import SubjectResult, clear_outputs, result_from_disk
from torchfit.pipeline.runtime import cpu_count
from torchfit.status import SubjectStatus

__all__ = [
    "MAX_RETRIES",
    "INSTALL_HINT",
    "RaySession",
    "require_ray",
    "plan",
    "start_ray",
    "run_on_ray",
]

log = logging.getLogger(__name__)

#: How many times a task whose worker died runs again.
MAX_RETRIES = 3
#: What to do when Ray is missing.
INSTALL_HINT = 'install it with `pip install "torchfit[ray]"` (or `pip install ray`)'

_MODELS: dict = {}  # per worker process: (template, device, dtype) -> BodyModel


def require_ray():
    """The ``ray`` module.

    Raises:
        ConfigError: Ray is not installed (the message says how to install it).
    """
    try:
        import ray
    except ImportError:
        raise ConfigError(f"run.executor: ray is not installed; {INSTALL_HINT}") from None
    return ray


def plan(run: RunConfig, cluster_cpus: int) -> tuple[int, int]:
    """``(workers, threads)``: tasks at once and torch threads per task.

    ``run.workers`` defaults to ``cluster_cpus // run.num_threads`` (one thread each when
    ``run.num_threads`` is not set); ``run.num_threads`` defaults to the CPUs per worker, so
    that threads x workers never exceeds the cluster's CPUs.
    """
    cluster_cpus = max(1, int(cluster_cpus))
    workers = run.workers or max(1, cluster_cpus // (run.num_threads or 1))
    threads = run.num_threads or max(1, cluster_cpus // workers)
    return workers, threads


def _fit_task(
    subjects: list[Subject],
    config: Config,
    fingerprints: dict[str, Fingerprint],
    threads: int,
) -> tuple[list[SubjectResult], dict[str, bytes]]:
    """One batch, on a worker: fit into a temporary folder, return the results and the files
    (paths relative to the run folder)."""
    from torchfit.body.model import BodyModel
    from torchfit.fit.contour_pool import set_contour_workers, start_contour_workers
    from torchfit.pipeline.run import fit_subjects
    from torchfit.pipeline.runtime import contour_workers_for, torch_dtype

    torch.set_num_threads(threads)
    # the task's CPUs: its fit's own and, on a GPU, the rest for the contour choice
    set_contour_workers(contour_workers_for(config.run, cores=threads))
    start_contour_workers()
    key = (config.model.template, config.run.device, config.run.dtype)
    if key not in _MODELS:
        _MODELS[key] = BodyModel(key[0], device=key[1], dtype=torch_dtype(key[2]))
    with tempfile.TemporaryDirectory(prefix="torchfit-") as tmp:
        folder = Path(tmp)
        tb = None
        if config.output.tensorboard:
            from torchfit.pipeline.tensorboard import TensorBoardCallback

            tb = TensorBoardCallback(folder / "tb", "fit")
        try:
            results = fit_subjects(subjects, _MODELS[key], config, folder, tb, None, fingerprints)
        finally:
            if tb is not None:
                tb.close()
        files = {
            path.relative_to(folder).as_posix(): path.read_bytes()
            for path in sorted(folder.rglob("*"))
            if path.is_file()
        }
    return results, files


def _reason(exc: Exception) -> str:
    """One line on why a task failed (Ray's errors carry the worker's traceback)."""
    cause = getattr(exc, "cause", None)
    if isinstance(cause, Exception):
        exc = cause
    lines = [line for line in str(exc).splitlines() if line.strip()]
    return f"{type(exc).__name__}: {lines[-1] if lines else ''}".rstrip(": ")


def _write_back(
    results: list[SubjectResult], files: dict[str, bytes], run_dir: Path
) -> list[SubjectResult]:
    """Write a task's files into the run folder; the results as read back from there."""
    for name, data in files.items():
        if name.startswith("tb/"):
            write_atomic(run_dir / name, data)
    out = []
    for result in results:
        folder = run_dir / result.name
        clear_outputs(folder)
        if result.status == SubjectStatus.FAILED:
            out.append(result)
            continue
        make_dirs(folder)
        own = sorted(n for n in files if n.startswith(f"{result.name}/"))
        last = f"{result.name}/{FINGERPRINT_FILE}"
        for name in [n for n in own if n != last] + [last]:
            write_atomic(run_dir / name, files[name])
        written = result_from_disk(result.name, folder)
        if written is None:
            raise OutputError(f"cannot read back the outputs written to {folder}")
        written.resumed = False
        out.append(written)
    return out


def _init(ray, run: RunConfig) -> int:
    """Connect to ``run.address`` (or start a local cluster); the cluster's CPUs."""
    if ray.is_initialized():
        return int(ray.cluster_resources().get("CPU", 1))
    quiet = {"logging_level": logging.WARNING, "log_to_driver": True}
    try:
        if run.address:
            ray.init(address=run.address, **quiet)
        else:
            # the workers import the torchfit the driver imports
            package = str(Path(__file__).resolve().parents[2])
            path = os.pathsep.join(p for p in (package, os.environ.get("PYTHONPATH")) if p)
            ray.init(
                num_cpus=cpu_count(),
                include_dashboard=False,
                runtime_env={"env_vars": {"PYTHONPATH": path}},
                **quiet,
            )
    except (ConnectionError, RuntimeError, ValueError) as exc:
        where = run.address or "a local cluster"
        raise ConfigError(f"run.address: cannot connect to Ray at {where}: {exc}") from None
    return int(ray.cluster_resources().get("CPU", 1))


def _check_fits(ray, threads: int, gpu: bool) -> None:
    """Raise ConfigError when no node of the cluster can run a task (Ray would wait forever)."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive")]
    cpus = max((r.get("CPU", 0) for r in nodes), default=0)
    if threads > cpus:
        raise ConfigError(
            f"run.num_threads: {threads} CPUs per task, but the largest Ray node has {cpus:g}"
        )
    if gpu and not any(r.get("GPU", 0) >= 1 for r in nodes):
        raise ConfigError("run.device: cuda, but no node of the Ray cluster has a GPU")


@dataclass
class RaySession:
    """A connection to a Ray cluster for one run: how many tasks at once, their threads."""

    ray: object
    workers: int
    threads: int
    gpu: bool
    cluster_cpus: int
    started_here: bool

    def close(self) -> None:
        """Stop the local cluster this run started (a cluster at an address stays)."""
        if self.started_here:
            self.ray.shutdown()


def start_ray(run: RunConfig) -> RaySession:
    """Connect to ``run.address`` (or start a local cluster) and check that a task fits a node.

    Raises:
        ConfigError: Ray is missing, the cluster cannot be reached, or no node has the CPUs
        (``run.num_threads``) or the GPU (``run.device: cuda``) a task asks for.
    """
    ray = require_ray()
    started_here = not ray.is_initialized() and not run.address
    cluster_cpus = _init(ray, run)
    try:
        workers, threads = plan(run, cluster_cpus)
        gpu = str(run.device).startswith("cuda")
        _check_fits(ray, threads, gpu)
    except ConfigError:
        if started_here:
            ray.shutdown()
        raise
    return RaySession(ray, workers, threads, gpu, cluster_cpus, started_here)


def run_on_ray(
    session: RaySession,
    subjects: list[Subject],
    config: Config,
    run_dir: Path,
    fingerprints: dict[str, Fingerprint],
    finish: Callable[[SubjectResult], None],
) -> None:
    """Fit ``subjects`` as Ray tasks, at most ``session.workers`` at once; ``finish`` each
    result.

    The tasks are the local run's batches of ``fit.batch_size`` subjects, so that the results
    are the local run's to the last digits whatever the batch does (with fewer subjects than
    workers x ``fit.batch_size``, some workers stay idle: lower ``fit.batch_size``).

    Raises:
        OutputError: the run folder cannot be written.
    """
    from torchfit.pipeline.run import batches

    ray, workers, threads = session.ray, session.workers, session.threads
    task = ray.remote(_fit_task).options(
        num_cpus=threads, num_gpus=1 if session.gpu else 0, max_retries=MAX_RETRIES
    )
    queue = batches(subjects, config.fit.batch_size)
    log.info(
        "ray: %d workers x %d torch threads (%d CPUs), %d batches",
        *(workers, threads, session.cluster_cpus, len(queue)),
    )
    pending: dict = {}
    while queue or pending:
        while queue and len(pending) < workers:
            batch = queue.pop(0)
            own = {s.name: fingerprints[s.name] for s in batch if s.name in fingerprints}
            pending[task.remote(batch, config, own, threads)] = batch
        ready, _ = ray.wait(list(pending), num_returns=1)
        batch = pending.pop(ready[0])
        try:
            results, files = ray.get(ready[0])
        except OutputError:
            raise
        except Exception as exc:  # the task failed for good (retries spent)
            reason = _reason(exc)
            log.error("batch %s failed: %s", [s.name for s in batch], reason)
            failed = SubjectStatus.FAILED
            results = [SubjectResult(s.name, failed, f"fit failed: {reason}") for s in batch]
            files = {}
        for result in _write_back(results, files, run_dir):
            finish(result)
