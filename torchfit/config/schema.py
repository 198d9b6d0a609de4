"""The configuration schema of the tools: one section per pipeline stage.

The sections compose the option dataclasses that the numeric packages own
(:class:`torchfit.fit.FitOptions`, :class:`torchfit.fit.StageOptions`,
:class:`torchfit.solver.LMOptions`, :class:`torchfit.parts.PartsOptions`, …) instead of
mirroring them; a section adds only what the pipeline itself decides (batching, the method,
the stage schedule). :mod:`torchfit.config.loader` checks a YAML file against it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Literal

from torchfit.errors import ConfigError
from torchfit.fit.bends import BendOptions
from torchfit.fit.prior import PriorOptions
from torchfit.fit.problem import FitOptions
from torchfit.fit.stages import StageOptions
from torchfit.image.chroma import ChromaKeyOptions
from torchfit.image.segment import SegmentationOptions
from torchfit.parts.options import PartsOptions
from torchfit.solver.options import LMOptions

__all__ = [
    "RunConfig",
    "DataConfig",
    "ModelConfig",
    "SilhouetteSource",
    "SegmentationConfig",
    "SolverConfig",
    "StageConfig",
    "FitPriorOptions",
    "FitBendOptions",
    "FitConfig",
    "OutputConfig",
    "PartsConfig",
    "Config",
]

#: A stage of the schedule (the fit's own options).
StageConfig = StageOptions
#: The ``parts`` section (the part decomposition's own options).
PartsConfig = PartsOptions


@dataclass(frozen=True)
class RunConfig:
    """Where and how a run executes.

    Attributes:
        name: the run's name; the run folder is ``runs/<name>`` unless ``out`` is set.
        out: the run folder.
        device: torch device of the fit (``cpu``, ``cuda``, ``cuda:1``).
        dtype: floating-point type of the fit's model, residuals and Jacobian; the solver's
            state is float64 either way (:data:`torchfit.fit.stages.SOLVER_DTYPE`).
        seed: random seed.
        resume: skip subjects whose outputs are complete.
        num_threads: torch CPU threads of each fit process (None: the CPUs divided by
            ``workers``, so that threads x workers never exceeds the CPUs).
        keep_heap: glibc malloc keeps freed memory (:func:`torchfit.solver.keep_heap`).
        executor: ``local`` (this process, batch after batch) or ``ray`` (each batch a Ray
            task; :mod:`torchfit.pipeline.ray_executor`).
        address: the Ray cluster (``auto``, ``HOST:PORT``, ``ray://HOST:PORT``); None starts
            a local cluster on this machine.
        workers: fits at once. Ray: tasks in flight (default: the cluster's CPUs divided by
            ``num_threads``). Local: how many fit processes share this machine (default 1),
            which sets the default ``num_threads``.
        contour_workers: processes of each fit that share its contour choice (drawing the
            model's outline, the nearest samples: CPU work, image by image), one
            thread each; 0 chooses in the fit's own process. None: 0 on the CPU, and on a
            GPU the CPUs left beside the fit (its CPUs less one). The results are the same
            either way (:mod:`torchfit.fit.contour_pool`).
    """

    name: str = "run"
    out: str | None = None
    device: str = "cpu"
    dtype: Literal["float32", "float64"] = "float64"
    seed: int = 0
    resume: bool = True
    num_threads: int | None = None
    keep_heap: bool = False
    executor: Literal["local", "ray"] = "local"
    address: str | None = None
    workers: int | None = None
    contour_workers: int | None = None

    def __post_init__(self) -> None:
        for key in ("num_threads", "workers"):
            value = getattr(self, key)
            if value is not None and value < 1:
                raise ConfigError(f"run.{key}: expected an integer >= 1, got {value!r}")
        if self.contour_workers is not None and self.contour_workers < 0:
            raise ConfigError(
                f"run.contour_workers: expected an integer >= 0, got {self.contour_workers!r}"
            )


@dataclass(frozen=True)
class DataConfig:
    """The dataset: a folder of subject folders, or a manifest file listing them.

    Attributes:
        root: the folder or manifest.
        subjects: restrict to these subject folder names.
    """

    root: str | None = None
    subjects: tuple[str, ...] | None = None


@dataclass(frozen=True)
class ModelConfig:
    """The template body model.

    Attributes:
        template: a shipped template name (``mpeg4_full``, ``mpeg4_simple``) or a path to a
            URDF file.
        scale_min, scale_max: bounds of every segment scale.
    """

    template: str = "mpeg4_full"
    scale_min: float = 0.4
    scale_max: float = 1.9


@dataclass(frozen=True)
class SilhouetteSource(SegmentationOptions):
    """The image side's own options (:class:`torchfit.image.SegmentationOptions`, inherited)
    and where the silhouettes come from: the tracker's ``segmentation`` section, and the base
    of the fit's (:class:`SegmentationConfig`).

    Attributes:
        method: ``background`` (subtraction against ``background/``, the first paper's),
            ``masks`` (your own silhouettes: a subject's ``masks/pose1`` … ``pose6``, a
            sequence's ``masks/`` with one image per frame in the frames' order; 8-bit, > 127
            is the person; no ``background/`` needed), ``chroma_key`` (a coloured screen, the
            second paper's; ``chroma_key`` below) or ``auto``: ``masks/`` where the folder has
            them, background subtraction otherwise.
        chroma_key: the key colour, tolerances and spill handling
            (:class:`torchfit.image.ChromaKeyOptions`).
    """

    method: Literal["auto", "background", "masks", "chroma_key"] = "auto"
    chroma_key: ChromaKeyOptions = field(default_factory=ChromaKeyOptions)


@dataclass(frozen=True)
class SegmentationConfig(SilhouetteSource):
    """The fit's ``segmentation`` section: :class:`SilhouetteSource` (the image side's options,
    ``method`` and ``chroma_key``) and the checks of the postures' silhouettes.

    Attributes:
        floor_reach_m: a posture whose silhouette's lowest pixel sees the floor further than
            this from the floor mark (metres) has lost its feet: the subject is ``poor_fit``
            with that reason (:func:`torchfit.pipeline.prepare.reach_floor`); None: not
            checked.
        floor_retry: with background subtraction and the shadow test, segment such a posture
            once more, the shadow test confined to the lowest ``floor_retry_band`` of the
            foreground (``shadow_band``) and with ``shadow_bridge``, and keep the new
            silhouette where it reaches the floor.
        floor_retry_band: see ``floor_retry``.
    """

    floor_reach_m: float | None = 1.0
    floor_retry: bool = False
    floor_retry_band: float = 0.15

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.floor_reach_m is not None and not (
            math.isfinite(self.floor_reach_m) and self.floor_reach_m > 0
        ):
            raise ConfigError(
                f"segmentation.floor_reach_m: expected a number > 0 or null, got "
                f"{self.floor_reach_m!r}"
            )
        if not 0.0 < self.floor_retry_band <= 1.0:
            raise ConfigError(
                f"segmentation.floor_retry_band: expected a value in (0, 1], got "
                f"{self.floor_retry_band!r}"
            )


@dataclass(frozen=True)
class SolverConfig(LMOptions):
    """The Levenberg–Marquardt options (:class:`torchfit.solver.LMOptions`, inherited) and the
    Jacobian the fit uses.

    Attributes:
        jacobian: ``autograd`` (the fit's own forward x reverse-mode Jacobian at the model
            contour), or ``forward``, ``reverse``, ``numeric``: the solver's generic
            forward-mode, reverse-mode or forward-difference Jacobian of the whole residual
            (slower; for checks). See :data:`torchfit.fit.JACOBIANS`.
        loss, loss_scale: as :class:`~torchfit.solver.LMOptions`, with the fit's defaults:
            Huber at 3 px on the contour distances e_P (e_M and the barriers stay least
            squares; a stage may set its own ``loss``). Chosen on the development set
            (benchmarks/RESULTS.md, "Robust fit").
        ftol, xtol: the fit's stopping tolerances (1e-6; the solver's own default, 1e-8, only
            lengthens a fit whose contour choice moves at every step).
        min_diag: a floor under Marquardt's scaling ``diag(JᵀJ)`` (1.0 for the fit; the
            solver's own default is 1e-12): a joint the camera cannot see (the far arm in a
            side view) has a near-zero Jacobian column and would otherwise get an undamped step
            of thousands of radians, be rejected again and again, and end the stage falsely
            with ``xtol``.
    """

    jacobian: Literal["autograd", "forward", "reverse", "numeric"] = "autograd"
    loss: Literal["linear", "huber", "cauchy"] = "huber"
    loss_scale: float = 3.0
    ftol: float = 1e-6
    xtol: float = 1e-6
    min_diag: float = 1.0

    def lm_options(self, max_iter: int | None = None) -> LMOptions:
        """These options as :class:`LMOptions` (``max_iter`` overrides, for a stage's own
        limit)."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(LMOptions)}
        if max_iter is not None:
            values["max_iter"] = max_iter
        return LMOptions(**values)


def _default_stages() -> tuple[StageOptions, ...]:
    return (
        StageOptions(
            name="legs_upper_body",
            scales=("legs", "upper_body"),
            joints=True,
            max_iter=30,
            loss="linear",
        ),
        StageOptions(name="all", scales=("all",), joints=True, max_iter=50),
    )


@dataclass(frozen=True)
class FitPriorOptions(PriorOptions):
    """:class:`PriorOptions` with the fit's defaults (the population prior at 0.3, the posture
    prior at 0.5): a ``fit.prior`` section that sets some keys keeps these for the others."""

    weight: float = 0.3
    pose_weight: float = 0.5


@dataclass(frozen=True)
class FitBendOptions(BendOptions):
    """:class:`BendOptions` with the fit's default weight (1.0): a ``fit.bends`` section that
    sets some keys keeps it for the others."""

    weight: float = 1.0


@dataclass(frozen=True)
class FitConfig(FitOptions):
    """The fitting problem (:class:`torchfit.fit.FitOptions`, inherited) and how the pipeline
    runs it.

    Attributes:
        stages: the stage schedule (:class:`torchfit.fit.StageOptions`).
        method: ``autograd_lm`` (the batched LM of this library) or ``minpack_rendered`` (the
            paper's own formulation: rendered contours, forward differences, MINPACK
            ``lmdif``, one subject at a time; the baseline).
        initial_guess: ``template`` or ``parts`` (the second paper's automatic start).
        batch_size: subjects solved together in one batched LM run.
        max_contour_rms_px: a fitted subject whose model contour is on average further than
            this from the person's contour in some posture (e_M, reference pixels: see
            ``reference_px_per_m``) gets status ``poor_fit`` (check its overlays).
        reference_px_per_m: the image residuals, the robust loss's scale and the pixel limits
            (``max_contour_rms_px``, ``pose_outlier_min_px``, ``bends.max_shift_px`` and
            ``bends.shown_px``) are in pixels of a camera that sees this many pixels per metre
            at the person (:func:`torchfit.fit.options.pixels_per_metre`), so that the priors
            weigh the same against the images on any camera. 210: the development sets'
            cameras (720x576, 197-223 pixels per metre), on which every weight was chosen; a
            1920x1080 camera framing the same view sees about 390. ``null``: the image's own
            pixels (each camera's resolution then changes the balance).
        pixel_noise_ratio: ``null`` (default) or ``ρ`` >= 0: the image residuals' factor
            ``sqrt((ρ² + 1) / (ρ² + (p / reference_px_per_m)²))`` instead of ``reference_px_per_m
            / p`` (``p`` the camera's pixels per metre), for contour errors partly of a fixed
            size in the image's pixels (:class:`torchfit.fit.FitOptions`).
        prior: the population prior over the log scales and the weight of a known height
            (:class:`torchfit.fit.prior.PriorOptions`; ``subject.yaml`` gives the facts).
        bends: the bent-joint marks (:class:`torchfit.fit.bends.BendOptions`): the flexed
            knee of posture 3 placed by the axes of the thigh and the shank.

    The defaults are the configuration the accuracy figures of benchmarks/RESULTS.md are
    measured with (``configs/benchmark.yaml`` states them): stages of 30 and 50 iterations,
    the population prior at 0.3 and the posture prior at 0.5, the knee's marks at 1.0, the
    side views' roll within 0.5 degrees and the person's contour pixels paired with model
    samples facing their way (``contour_orientation_px`` 8). (The classes of
    :mod:`torchfit.fit` keep their own neutral defaults, all of these off, for library use.)
    """

    side_roll_max_deg: float | None = 0.5
    contour_orientation_px: float = 8.0
    stages: tuple[StageOptions, ...] = field(default_factory=_default_stages)
    method: Literal["autograd_lm", "minpack_rendered"] = "autograd_lm"
    initial_guess: Literal["template", "parts"] = "template"
    batch_size: int = 4
    max_contour_rms_px: float = 15.0
    reference_px_per_m: float | None = 210.0
    prior: FitPriorOptions = field(default_factory=FitPriorOptions)
    bends: FitBendOptions = field(default_factory=FitBendOptions)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.batch_size < 1:
            raise ConfigError(f"fit.batch_size: expected an integer >= 1, got {self.batch_size!r}")
        if not self.stages:
            raise ConfigError("fit.stages: expected at least one stage, got none")


@dataclass(frozen=True)
class OutputConfig:
    """What a run writes.

    Attributes:
        overlays: overlay_pose<j>.png per subject.
        mesh_format: the fitted body's mesh file, ``glb`` or ``obj``.
        tensorboard: TensorBoard event files under ``tb/``.
    """

    overlays: bool = True
    mesh_format: Literal["glb", "obj"] = "glb"
    tensorboard: bool = True


@dataclass(frozen=True)
class Config:
    """The whole configuration of a tool run."""

    run: RunConfig = field(default_factory=RunConfig)
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    parts: PartsConfig = field(default_factory=PartsConfig)
