"""Configuration schema (one dataclass per stage), YAML loading and ``--set`` overrides.

A config file is YAML whose top-level keys are the fields of :class:`Config`. Every key is
checked against the schema: an unknown key or a value of the wrong type raises
:class:`~torchfit.errors.ConfigError` naming the dotted key and the file. Overrides use dotted
keys, ``--set solver.max_iter=50``; the value is parsed as YAML (``50`` is an int, ``[1, 2]`` a
list, ``null`` None).
"""

from __future__ import annotations

import dataclasses
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Union

import yaml

from torchfit.errors import ConfigError
from torchfit.image.segment import SegmentationOptions

if TYPE_CHECKING:
    from torchfit.solver import LMOptions

__all__ = [
    "RunConfig",
    "DataConfig",
    "ModelConfig",
    "SegmentationConfig",
    "SolverConfig",
    "StageConfig",
    "FitConfig",
    "OutputConfig",
    "PartsConfig",
    "Config",
    "load_config",
    "config_from_dict",
    "config_to_dict",
    "apply_overrides",
    "save_config",
    "parse_yaml",
]


@dataclass
class RunConfig:
    """Where and how a run executes."""

    name: str = "run"
    out: str | None = None  # run folder; default runs/<name>
    device: str = "cpu"
    dtype: Literal["float32", "float64"] = "float64"
    seed: int = 0
    resume: bool = True  # skip subjects whose outputs are complete
    num_threads: int | None = None  # torch CPU threads (None: torch's default)
    keep_heap: bool = False  # glibc malloc keeps freed memory (torchfit.solver.keep_heap)


@dataclass
class DataConfig:
    """The dataset: a folder of subject folders, or a manifest file listing them."""

    root: str | None = None
    subjects: list[str] | None = None  # restrict to these subject folder names


@dataclass
class ModelConfig:
    """The template body model."""

    template: str = "mpeg4_full"  # a shipped template name or a path to a URDF file
    scale_min: float = 0.4
    scale_max: float = 1.9


# The segmentation options are owned by the numeric code (torchfit.image.segment); the
# config schema composes them unchanged (a frozen dataclass: replace fields, do not assign).
SegmentationConfig = SegmentationOptions


@dataclass
class SolverConfig:
    """Levenberg–Marquardt options: the fields of :class:`torchfit.solver.LMOptions` (same
    names, meanings and defaults) plus the Jacobian choice."""

    max_iter: int = 100
    ftol: float = 1e-8
    xtol: float = 1e-8
    gtol: float = 1e-10
    initial_damping: float = 1e-3
    min_diag: float = 1e-12
    max_diag: float = 1e32
    accept_ratio: float = 1e-4
    max_bad_steps: int = 10
    step_bound: float | None = 100.0
    fold_batch: bool = True
    geodesic_acceleration: bool = False
    accel_ratio: float = 0.75
    max_nfev: int | None = None
    jacobian: Literal["autograd", "forward", "reverse", "numeric"] = "autograd"

    def lm_options(self, max_iter: int | None = None) -> LMOptions:
        """These options as :class:`torchfit.solver.LMOptions` (``max_iter`` overrides, for a
        stage's own limit)."""
        from torchfit.solver import LMOptions

        values = {
            f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "jacobian"
        }
        if max_iter is not None:
            values["max_iter"] = max_iter
        return LMOptions(**values)


@dataclass
class StageConfig:
    """One stage of the fit schedule."""

    name: str = "all"
    scales: list[str] = field(default_factory=lambda: ["all"])  # free scale groups
    joints: bool = True  # optimise the per-pose free joint angles
    root: bool = True  # optimise the per-pose floor translation and rotation
    max_iter: int | None = None  # overrides solver.max_iter for this stage


@dataclass
class FitConfig:
    """The fitting problem (first paper, sections 6–8)."""

    stages: list[StageConfig] = field(
        default_factory=lambda: [
            StageConfig(name="legs_upper_body", scales=["legs", "upper_body"], joints=True),
            StageConfig(name="all", scales=["all"], joints=True),
        ]
    )
    poses: list[int] = field(default_factory=lambda: [1, 2, 3, 4, 5, 6])
    initial_guess: Literal["template", "parts"] = "template"
    batch_size: int = 4  # subjects solved together in one batched LM run
    # a fitted subject whose model contour is on average further than this from the
    # person's contour in some pose (e_M, pixels) gets status "poor_fit" (check its overlays)
    max_contour_rms_px: float = 15.0
    # per-pose free joints, e.g. {pose3: [l_knee_flexion, ...]}; default: design.md section 4
    free_joints: dict[str, list[str]] | None = None
    translation_max_m: float = 0.15  # floor translation interval, each axis
    yaw_max_deg: float = 15.0  # yaw interval around the nominal view
    tilt_max_deg: float = 5.0  # roll / pitch interval
    barrier_weight: float = 100.0  # e_B slope outside an interval
    samples_per_edge: int = 4  # model contour candidates per mesh edge
    contour_tolerance_px: float = 1.0  # a sample within this of the rendered contour is on it
    contour_stride: int = 1  # use every n-th person contour pixel in e_P
    # treat the pixels the segmentation's shadow test removed as uncertain rather than as
    # background: no e_P from person contour pixels within shadow_margin_px of them, no e_M
    # from model contour points on them (has an effect with segmentation.shadow_test only)
    ignore_shadow: bool = True
    shadow_margin_px: int = 2


@dataclass
class OutputConfig:
    """What a run writes."""

    overlays: bool = True
    mesh_format: Literal["glb", "obj"] = "glb"
    tensorboard: bool = True


@dataclass
class PartsConfig:
    """Silhouette part decomposition (second paper): spline, curvature extrema, rules, wrists.

    Lengths given as fractions are relative to the silhouette height ``H`` (curve options) or to
    the 2-D trunk length ``T`` (neck cut middle to crotch; joint offsets), so that they do not
    depend on the image scale. See ``torchfit.parts`` for the rules.
    """

    smoothing_px: float = 1.0  # RMS distance spline - contour pixels (0: interpolation)
    point_spacing: int = 1  # use every n-th contour pixel
    min_curvature: float = 8.0  # significance: |curvature| * H above this
    min_separation: float = 0.02  # extrema closer than this * H along the outline merge
    hand_exclusion: float = 0.25  # inner-elbow candidates > this * T above the neck are hands
    wrists: bool = True  # find the wrists from skin colour
    skin_threshold: float = 3.0  # Mahalanobis distance to the face's skin chromaticity
    hand_start: float = 0.4  # hand pixels lie beyond this fraction of elbow -> hand tip
    face_band: float = 0.45  # skin is learnt this fraction of the way from the neck to the top
    # Systematic cut-point -> joint-centre corrections (torchfit.parts.JointOffsets):
    # (down, out) in units of the 2-D trunk length, per joint; the median of label -> projected
    # joint centre on the synthetic development subjects (seed 1000), never the test set:
    # `python benchmarks/calibrate_parts.py --data <dev set>` with configs/stereo.yaml.
    offset_back: list[float] = field(default_factory=lambda: [-0.184, 0.0])
    offset_neck: list[float] = field(default_factory=lambda: [0.060, 0.0])
    offset_shoulder: list[float] = field(default_factory=lambda: [0.049, 0.058])
    offset_elbow: list[float] = field(default_factory=lambda: [0.014, 0.028])
    offset_wrist: list[float] = field(default_factory=lambda: [-0.009, 0.017])
    # Stereo correspondence: refine each joint's right-view pixel by matching the two
    # silhouettes along the epipolar line around its outline anchors (false: the paper's
    # independent labelling of both views).
    stereo_match: bool = True
    match_radius: float = 0.1  # matching window half-size, * T
    match_search_px: float = 8.0  # search +- this along the epipolar line, pixels


@dataclass
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


# --------------------------------------------------------------------------------------------
# YAML: PyYAML follows YAML 1.1, where ``1e-3`` is a string; accept YAML 1.2 floats.


class _Loader(yaml.SafeLoader):
    pass


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def parse_yaml(text: str) -> Any:
    """``yaml.safe_load`` that also reads ``1e-3`` as a float (YAML 1.2 numbers)."""
    return yaml.load(text, Loader=_Loader)  # noqa: S506 - a SafeLoader subclass


# --------------------------------------------------------------------------------------------
# Conversion with type checking


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _convert(value: Any, tp: Any, key: str, source: str) -> Any:
    """Check ``value`` against the annotation ``tp`` and convert it (dicts to dataclasses)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)

    def fail(expected: str) -> ConfigError:
        return ConfigError(
            f"{source}: key '{key}' expects {expected}, got {type(value).__name__} {value!r}"
        )

    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _convert(value, arg, key, source)
            except ConfigError as exc:
                errors.append(exc)
        if len(errors) == 1:
            raise errors[0]
        raise fail(" or ".join(_type_name(a) for a in args))
    if origin is Literal:
        if value not in args:
            raise ConfigError(f"{source}: key '{key}' must be one of {list(args)}, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise fail(f"a mapping of {tp.__name__} fields")
        return _dataclass_from_dict(tp, value, key, source)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise fail(f"a list of {_type_name(args[0]) if args else 'values'}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise fail(f"a list of {len(args)} values")
            return tuple(
                _convert(v, a, f"{key}[{i}]", source)
                for i, (v, a) in enumerate(zip(value, args, strict=True))
            )
        inner = args[0] if args else Any
        out = [_convert(v, inner, f"{key}[{i}]", source) for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    if origin is dict:
        if not isinstance(value, dict):
            raise fail("a mapping")
        ktp, vtp = args if args else (Any, Any)
        return {
            _convert(k, ktp, f"{key}.{k}", source): _convert(v, vtp, f"{key}.{k}", source)
            for k, v in value.items()
        }
    if tp is bool:
        if not isinstance(value, bool):
            raise fail("a boolean (true/false)")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise fail("an integer")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise fail("a number")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise fail("a string")
        return value
    raise ConfigError(f"{source}: key '{key}' has an unsupported schema type {tp!r}")


def _dataclass_from_dict(cls: type, data: dict, prefix: str, source: str) -> Any:
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = [k for k in data if k not in names]
    if unknown:
        where = f"{prefix}." if prefix else ""
        raise ConfigError(
            f"{source}: unknown key '{where}{unknown[0]}' (valid keys"
            f"{' under ' + repr(prefix) if prefix else ''}: {', '.join(sorted(names))})"
        )
    kwargs = {
        k: _convert(v, hints[k], f"{prefix}.{k}" if prefix else k, source) for k, v in data.items()
    }
    return cls(**kwargs)


def config_from_dict(data: dict | None, source: str = "<dict>", schema: type = Config) -> Any:
    """Build a config dataclass from a plain dict, checking every key and type.

    Args:
        data: nested mapping (as loaded from YAML); ``None`` gives the defaults.
        source: name used in error messages (usually the file path).
        schema: the dataclass to build (default :class:`Config`).

    Raises:
        ConfigError: naming the dotted key and ``source``.
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the top level must be a mapping, got {type(data).__name__}")
    config = _dataclass_from_dict(schema, data, "", source)
    if isinstance(config, Config):
        poses = config.fit.poses
        if not poses or len(set(poses)) != len(poses) or not set(poses) <= set(range(1, 7)):
            raise ConfigError(
                f"{source}: key 'fit.poses' must list distinct postures from 1..6, got {poses}"
            )
    return config


def config_to_dict(config: Any) -> dict:
    """The plain-dict form of a config dataclass (tuples become lists), ready for YAML."""

    def plain(v: Any) -> Any:
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        return v

    return plain(dataclasses.asdict(config))


def apply_overrides(data: dict, overrides: list[str], source: str = "--set") -> dict:
    """Apply ``a.b.c=value`` overrides to a nested dict (values parsed as YAML).

    Raises:
        ConfigError: for an override without ``=`` or a value that is not valid YAML.
    """
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"{source}: override {item!r} must look like key.sub=value")
        key, raw = item.split("=", 1)
        key = key.strip()
        if not key:
            raise ConfigError(f"{source}: override {item!r} has an empty key")
        try:
            value = parse_yaml(raw) if raw.strip() else ""
        except yaml.YAMLError as exc:
            raise ConfigError(f"{source}: value of '{key}' is not valid YAML: {exc}") from exc
        node = data
        parts = key.split(".")
        for part in parts[:-1]:
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            if not isinstance(child, dict):
                raise ConfigError(f"{source}: cannot set '{key}': '{part}' is not a mapping")
            node = child
        node[parts[-1]] = value
    return data


def load_config(
    path: str | Path | None,
    overrides: list[str] | None = None,
    schema: type = Config,
) -> Any:
    """Load a YAML config file, apply ``--set`` overrides and check it against ``schema``.

    Args:
        path: the YAML file; ``None`` starts from the defaults.
        overrides: ``["solver.max_iter=50", ...]``.
        schema: the dataclass to build (default :class:`Config`).

    Raises:
        ConfigError: for a missing file, invalid YAML, an unknown key or a wrong type; the
            message names the key and the file.
    """
    source = str(path) if path is not None else "<defaults>"
    data: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"config file not found: {path}")
        try:
            data = parse_yaml(path.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: invalid YAML: {exc}") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: the top level must be a mapping, got {type(data).__name__}")
    if overrides:
        apply_overrides(data, overrides)
        source = f"{source} (with --set overrides)"
    return config_from_dict(data, source, schema)


def save_config(config: Any, path: str | Path) -> None:
    """Write the resolved config as YAML."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(yaml.safe_dump(config_to_dict(config), sort_keys=False))
